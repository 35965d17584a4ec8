#version 450 core
#extension GL_ARB_shader_draw_parameters : require
// Tree splats (Zach, Mantler & Karner 2002, 5.2): one draw per (group, model)
// run draws a prefix of the model's prefix-ordered points for each of the run's
// instances. The instance's 3 x 4 model -> world matrix is an instanced
// attribute (baseInstance picks the run's first instance); the splat's world
// radius depends on the prefix length, so it is a per-draw value read from a
// storage buffer by gl_DrawIDARB (multi-draw allows no per-draw uniform).
// Camera-relative like mesh.vert.glsl: the eye is subtracted before the
// rotation-only view, so large world coordinates keep their precision.

layout(std430, binding = 5) readonly buffer DrawRadius { float draw_radius[]; };

uniform mat4 u_view_projection;  // projection @ view-rotation (no translation)
uniform vec3 u_eye;              // world-space eye
uniform float u_pixel_scale;     // viewport height / tan(fov_y / 2): diameter in px = radius * this / w
uniform vec2 u_size_range;       // gl_PointSize clamp, pixels

in vec3 in_pos;                  // model-space point
in vec3 in_normal;               // model-space unit normal
in vec4 in_color;                // rgb (normalised bytes), a unused
in vec4 in_row0;                 // per instance: rows 0-2 of the model -> world matrix
in vec4 in_row1;
in vec4 in_row2;
in float in_scale;               // per instance: the matrix's uniform scale, cbrt |det|

flat out vec3 v_normal;          // world-space, turned towards the viewer
flat out vec3 v_color;

void main() {
    mat3 a = transpose(mat3(in_row0.xyz, in_row1.xyz, in_row2.xyz));
    vec3 rel = a * in_pos + (vec3(in_row0.w, in_row1.w, in_row2.w) - u_eye);
    vec3 n = normalize(a * in_normal);
    // Splats are discs facing the camera: light the side the viewer sees.
    v_normal = dot(n, rel) > 0.0 ? -n : n;
    v_color = in_color.rgb;
    gl_Position = u_view_projection * vec4(rel, 1.0);
    float radius = draw_radius[gl_DrawIDARB] * in_scale;
    gl_PointSize = clamp(radius * u_pixel_scale / max(gl_Position.w, 1e-6), u_size_range.x, u_size_range.y);
}
