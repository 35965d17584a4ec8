#version 330 core
// Flat (algorithm 0): no normals needed. The face normal is the cross product
// of the screen-space derivatives of the position; it always faces the viewer,
// so the winding of simplified meshes does not matter.

in vec3 v_rel;
in vec3 v_colour;
flat in uint v_flags;
out vec4 f_color;

void main() {
    vec3 n = normalize(cross(dFdx(v_rel), dFdy(v_rel)));
    f_color = vec4(mark(v_colour, v_flags) * light(n), 1.0);
}
