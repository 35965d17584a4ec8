#version 330 core
// Lit (algorithm 1): smooth normals computed at upload, lit per vertex (Gouraud);
// the fragment only modulates the interpolated light.

in vec3 v_rel;
in vec3 v_colour;
flat in uint v_flags;
in vec3 v_light;
in float v_specular;
out vec4 f_color;

void main() {
    f_color = vec4(mark(v_colour, v_flags) * v_light + vec3(v_specular), 1.0);
}
