#version 330 core
// Geomorph: mesh.vert.glsl with a second position per vertex, the vertex of the
// next coarser level it morphs to (Zach 2002, 3.4). The drawn position is
// mix(target, pos, u_weight): u_weight = 1 is the level itself, 0 looks exactly
// like the coarser level. The blend is written as w·pos + (1 − w)·target rather
// than with mix(), whose rounding GLSL leaves to the implementation, so that
// both ends reproduce their levels bit for bit.

uniform mat4 u_view_projection;  // projection @ view-rotation (no translation)
uniform vec3 u_eye;              // world-space eye
uniform float u_weight;          // morph weight in [0, 1], one per draw

in vec3 in_pos;                  // world-space position (this, the finer level)
in vec4 in_tint;                 // the object's colour
in vec3 in_target;               // world-space position of the coarser vertex it morphs to
out vec3 v_rel;                  // position relative to the eye
flat out vec3 v_tint;

void main() {
    vec3 pos = in_pos * u_weight + in_target * (1.0 - u_weight);
    v_rel = pos - u_eye;
    v_tint = in_tint.rgb;
    gl_Position = u_view_projection * vec4(v_rel, 1.0);
}
