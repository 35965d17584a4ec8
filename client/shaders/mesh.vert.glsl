#version 330 core
// One vertex shader for every mesh algorithm (ALGORITHM, STAGE_VERTEX and
// mesh_common.glsl are inserted after this line by the renderer).
//
// Camera-relative transform: positions are shifted by the eye before the
// rotation-only view and the projection, so large world coordinates keep their
// precision near the camera (and the screen-space derivatives stay clean).
//
// Geomorph (Zach 2002, 3.4): every vertex carries its morph target, the vertex
// of the next coarser level it morphs to (the position itself until the renderer
// is given one), with that vertex's normal (lit morphs its shading too), and
// every draw a weight; its colour blends toward the target's colour the same way.
// The blend is written w·pos + (1 − w)·target
// rather than with mix(), whose rounding GLSL leaves to the implementation, so
// that w = 1 is the level itself and w = 0 the coarser level, bit for bit (also
// under fused multiply-add: the other product is then exactly 0).
//
// Per-draw data are instanced attributes (divisor 1): each indirect command
// draws one instance with baseInstance = its row, so no per-draw uniform.

uniform mat4 u_view_projection;  // projection @ view-rotation (no translation)
uniform vec3 u_eye;              // world-space eye

in vec3 in_pos;                  // world-space position (this level)
in vec3 in_target;               // world-space position it morphs to
in vec4 in_normal;               // smooth normal, n · ½ + ½ in normalised bytes (lit only)
in vec4 in_target_normal;        // the morph target's normal, the same way (lit only)
in vec4 in_colour;               // the vertex's colour; a = 1 when it has one, 0: the object's tint
in vec4 in_target_colour;        // the morph target's colour, the same way
in vec2 in_uv;                   // texture coordinates (textured only; v up)
in float in_weight;              // per draw: morph weight in [0, 1] (1: static)
in float in_level;               // per draw: continuous level, for the false colours
in vec4 in_tint;                 // per draw: the object's colour
in uint in_flags;                // per draw: FLAG_MORPH
in int in_tex_class;             // per draw: the texture's size class, -1: none (textured only)
in float in_tex_layer;           // per draw: its layer in that class's texture array

out vec3 v_rel;                  // position relative to the eye
out vec3 v_colour;               // the surface colour (the data's, the tint, or the level's false colour)
flat out uint v_flags;
#if ALGORITHM == 1
out vec3 v_light;                // Gouraud: the lighting, per vertex
out float v_specular;
#endif
#if ALGORITHM == 2
out vec2 v_uv;
flat out int v_tex_class;
flat out float v_tex_layer;
#endif

void main() {
    float w = in_weight;
    vec3 pos = in_pos * w + in_target * (1.0 - w);
    v_rel = pos - u_eye;
    vec4 own = in_colour * w + in_target_colour * (1.0 - w);
    vec3 data = mix(in_tint.rgb, own.rgb, own.a);
    v_colour = u_false_colour ? level_colour(in_level) : (u_object_colours ? in_tint.rgb : data);
    v_flags = in_flags;
#if ALGORITHM == 1
    vec3 n = (in_normal.xyz * w + in_target_normal.xyz * (1.0 - w)) * 2.0 - 1.0;
    n = dot(n, n) > 1e-6 ? normalize(n) : u_up;
    vec3 to_eye = normalize(-v_rel);
    if (dot(n, to_eye) < 0.0) n = -n;  // winding is not consistent after simplification: face the viewer
    v_light = light(n);
    vec3 h = normalize(u_sun + to_eye);
    v_specular = pow(max(dot(n, h), 0.0), 24.0) * 0.25;
#endif
#if ALGORITHM == 2
    v_uv = in_uv;
    v_tex_class = in_tex_class;
    v_tex_layer = in_tex_layer;
#endif
    gl_Position = u_view_projection * vec4(v_rel, 1.0);
}
