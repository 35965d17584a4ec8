#version 330 core
// A sky gradient from the horizon to the zenith above, a hazy ground colour
// below, and a glow around the sun: what a scene is seen against.

uniform vec3 u_up;       // unit world up
uniform vec3 u_sun;      // unit direction towards the sun
uniform vec3 u_zenith;
uniform vec3 u_horizon;
uniform vec3 u_below;    // the haze below the horizon, where no ground is drawn

in vec3 v_direction;
out vec4 f_color;

void main() {
    vec3 d = normalize(v_direction);
    float e = dot(d, u_up);
    vec3 sky = e >= 0.0 ? mix(u_horizon, u_zenith, pow(e, 0.6))
                        : mix(u_horizon, u_below, smoothstep(0.0, 0.08, -e));
    float glow = pow(max(dot(d, u_sun), 0.0), 64.0) * step(0.0, e);
    f_color = vec4(sky + vec3(0.35, 0.30, 0.20) * glow, 1.0);
}
