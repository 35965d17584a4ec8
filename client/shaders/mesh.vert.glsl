#version 330 core
// Camera-relative transform: positions are shifted by the eye before the
// rotation-only view and the projection, so large world coordinates keep their
// precision near the camera (and the screen-space derivatives stay clean).

uniform mat4 u_view_projection;  // projection @ view-rotation (no translation)
uniform vec3 u_eye;              // world-space eye

in vec3 in_pos;                  // world-space position
in vec4 in_tint;                 // the object's colour (per vertex: no uniform change between draws)
out vec3 v_rel;                  // position relative to the eye
flat out vec3 v_tint;

void main() {
    v_rel = in_pos - u_eye;
    v_tint = in_tint.rgb;
    gl_Position = u_view_projection * vec4(v_rel, 1.0);
}
