#version 330 core
// Textured (algorithm 2): a procedural world-space stone-and-brick texture,
// projected triplanar over the surface's colour and lit like flat. Deliberately heavier per pixel (three
// brick lookups and four octaves of value noise per projection) so that its
// fill cost is measurably higher than the other algorithms'.
//
// Precision: the pattern repeats every 64 m, and u_eye_wrap is the eye modulo
// 64 m (computed in double on the CPU), so v_rel + u_eye_wrap is the world
// position modulo 64 m with full float precision however far from the origin.

uniform vec3 u_eye_wrap;

in vec3 v_rel;
in vec3 v_colour;
flat in uint v_flags;
out vec4 f_color;

const float PERIOD = 64.0;

float hash(vec2 cell, float period) {
    cell = mod(cell, period);
    return fract(sin(dot(cell, vec2(127.1, 311.7))) * 43758.5453);
}

float value_noise(vec2 p, float period) {
    vec2 i = floor(p), f = fract(p);
    vec2 u = f * f * (3.0 - 2.0 * f);
    float a = hash(i, period), b = hash(i + vec2(1.0, 0.0), period);
    float c = hash(i + vec2(0.0, 1.0), period), d = hash(i + vec2(1.0, 1.0), period);
    return mix(mix(a, b, u.x), mix(c, d, u.x), u.y);
}

float fbm(vec2 p) {  // 4 octaves, periodic over PERIOD metres
    float sum = 0.0, amp = 0.5, freq = 2.0;
    for (int o = 0; o < 4; ++o) {
        sum += amp * value_noise(p * freq, PERIOD * freq);
        amp *= 0.5;
        freq *= 2.0;
    }
    return sum;
}

// Bricks 0.5 × 0.25 m in running bond: brightness of the brick (varies per brick) or dark mortar.
float brick(vec2 p) {
    vec2 uv = p / vec2(0.5, 0.25);
    float row = floor(uv.y);
    uv.x += 0.5 * mod(row, 2.0);
    vec2 cell = floor(uv), f = fract(uv);
    vec2 edge = min(f, 1.0 - f) * vec2(0.5, 0.25);
    float mortar = smoothstep(0.008, 0.018, min(edge.x, edge.y));
    float tone = 0.8 + 0.35 * hash(cell, PERIOD * 2.0) + 0.25 * (fbm(p) - 0.5);
    return mix(0.45, tone, mortar);
}

void main() {
    vec3 n = normalize(cross(dFdx(v_rel), dFdy(v_rel)));
    vec3 p = v_rel + u_eye_wrap;
    vec3 w = pow(abs(n), vec3(4.0));
    w /= w.x + w.y + w.z;
    float pattern = w.x * brick(p.yz) + w.y * brick(p.xz) + w.z * brick(p.xy);
    f_color = vec4(mark(v_colour, v_flags) * pattern * light(n), 1.0);
}
