#version 450 core
// Round splats lit like the meshes (mesh.frag.glsl): a hemisphere term along the
// camera's up plus a camera-borne key light, here with the points' own normals
// and colours. Outside the inscribed disc of the point sprite is discarded, so
// splats are round and the depth test sees discs, not squares.

uniform vec3 u_up;     // unit up (the camera's)
uniform vec3 u_sun;    // unit direction towards the key light, world space

flat in vec3 v_normal;
flat in vec3 v_color;
out vec4 f_color;

const vec3 SKY = vec3(0.80, 0.88, 1.00);
const vec3 GROUND = vec3(0.42, 0.38, 0.33);

void main() {
    vec2 d = gl_PointCoord * 2.0 - 1.0;
    if (dot(d, d) > 1.0) discard;
    float h = dot(v_normal, u_up) * 0.5 + 0.5;
    vec3 ambient = mix(GROUND, SKY, h) * 0.5;
    float sun = max(dot(v_normal, u_sun), 0.0) * 0.6;
    f_color = vec4(v_color * (ambient + vec3(sun)), 1.0);
}
