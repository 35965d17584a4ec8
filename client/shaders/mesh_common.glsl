// Shared by every mesh program, inserted by the renderer after the #version line
// of each stage (with ALGORITHM 0 flat, 1 lit, 2 textured and STAGE_VERTEX or
// STAGE_FRAGMENT defined): the lighting and the false-colour mode, so the three
// algorithms differ only in where the normal comes from and what the surface is.

uniform vec3 u_up;             // world up (the camera's up vector)
uniform vec3 u_sun;            // unit direction towards the sun (or the camera's key light), world space
uniform vec2 u_light_mix;      // weights of the hemisphere and of the sun
uniform bool u_false_colour;   // colour by drawn level, stripe the morphing draws
uniform bool u_object_colours; // every object in its tint, whatever colours its payload has
uniform float u_level_scale;   // level drawn in the ramp's finest colour

const vec3 SKY = vec3(0.80, 0.88, 1.00);
const vec3 GROUND = vec3(0.42, 0.38, 0.33);
const uint FLAG_MORPH = 1u;

// Hemisphere (sky above, ground below, along the camera's up) plus the sun, or a
// camera-borne key light: every visible face is lit, and the angle still separates faces.
// A fixed sun leaves the faces turned from it to the hemisphere, which then weighs more.
vec3 light(vec3 n) {
    float h = dot(n, u_up) * 0.5 + 0.5;
    vec3 ambient = mix(GROUND, SKY, h) * u_light_mix.x;
    float sun = max(dot(n, u_sun), 0.0) * u_light_mix.y;
    return ambient + vec3(sun);
}

// Coarse → fine: blue, cyan, green, yellow, red (Funkhouser & Séquin's Fig. 8 colours levels).
vec3 level_colour(float level) {
    float t = clamp(level / max(u_level_scale, 1e-6), 0.0, 1.0) * 4.0;
    const vec3 RAMP[5] = vec3[5](vec3(0.15, 0.30, 0.95), vec3(0.10, 0.80, 0.90), vec3(0.20, 0.85, 0.20),
                                 vec3(0.95, 0.85, 0.10), vec3(0.95, 0.20, 0.10));
    int i = min(int(t), 3);
    return mix(RAMP[i], RAMP[i + 1], t - float(i));
}

#ifdef STAGE_FRAGMENT
// Morphing draws in magenta diagonal stripes (as Zach's Fig. 9 marks them), under the same lighting.
vec3 mark(vec3 colour, uint flags) {
    if (u_false_colour && (flags & FLAG_MORPH) != 0u && mod(gl_FragCoord.x + gl_FragCoord.y, 8.0) < 4.0)
        return vec3(1.0, 0.0, 1.0);
    return colour;
}
#endif
