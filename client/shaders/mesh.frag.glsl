#version 330 core
// Flat shading without normals: the face normal is the cross product of the
// screen-space derivatives of the position. It always faces the viewer, so the
// winding of simplified meshes does not matter. A hemisphere term (sky above,
// ground below, along the camera's up) plus a camera-borne key light keeps
// shapes readable from any side.

uniform vec3 u_up;     // world up (the camera's up vector)
uniform vec3 u_sun;    // unit direction towards the key light, world space

in vec3 v_rel;
flat in vec3 v_tint;   // per-object colour
out vec4 f_color;

const vec3 SKY = vec3(0.80, 0.88, 1.00);
const vec3 GROUND = vec3(0.42, 0.38, 0.33);

void main() {
    vec3 n = normalize(cross(dFdx(v_rel), dFdy(v_rel)));
    float h = dot(n, u_up) * 0.5 + 0.5;
    vec3 ambient = mix(GROUND, SKY, h) * 0.5;
    float sun = max(dot(n, u_sun), 0.0) * 0.6;
    f_color = vec4(v_tint * (ambient + vec3(sun)), 1.0);
}
