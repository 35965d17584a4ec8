#version 330 core
// Textured (algorithm 2): the representation's own base-colour texture where it has
// one (its draw row names the texture array of its size class and its layer there,
// client.textures), lit like flat; where it has none, a procedural world-space
// stone-and-brick texture, projected triplanar over the surface's colour.
// The procedural one is deliberately heavier per pixel (three brick lookups and
// four octaves of value noise per projection) so that its fill cost is measurably
// higher than the other algorithms'.
//
// GLSL 3.30 indexes sampler arrays by constants only, so each class has its own
// sampler and a switch picks it; every fragment of a draw takes the same case. The
// UV derivatives are taken before the switch (textureGrad), where control flow is
// uniform, so the mipmap level is well defined.
//
// Precision: the pattern repeats every 64 m, and u_eye_wrap is the eye modulo
// 64 m (computed in double on the CPU), so v_rel + u_eye_wrap is the world
// position modulo 64 m with full float precision however far from the origin.

uniform vec3 u_eye_wrap;
uniform sampler2DArray u_texture0, u_texture1, u_texture2, u_texture3, u_texture4,
                       u_texture5, u_texture6, u_texture7, u_texture8, u_texture9;  // 8 .. 4096 px

in vec3 v_rel;
in vec3 v_colour;
flat in uint v_flags;
in vec2 v_uv;
flat in int v_tex_class;
flat in float v_tex_layer;
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

vec3 texel(vec2 dx, vec2 dy) {
    vec3 at = vec3(v_uv, v_tex_layer);
    switch (v_tex_class) {
        case 0: return textureGrad(u_texture0, at, dx, dy).rgb;
        case 1: return textureGrad(u_texture1, at, dx, dy).rgb;
        case 2: return textureGrad(u_texture2, at, dx, dy).rgb;
        case 3: return textureGrad(u_texture3, at, dx, dy).rgb;
        case 4: return textureGrad(u_texture4, at, dx, dy).rgb;
        case 5: return textureGrad(u_texture5, at, dx, dy).rgb;
        case 6: return textureGrad(u_texture6, at, dx, dy).rgb;
        case 7: return textureGrad(u_texture7, at, dx, dy).rgb;
        case 8: return textureGrad(u_texture8, at, dx, dy).rgb;
        default: return textureGrad(u_texture9, at, dx, dy).rgb;
    }
}

void main() {
    vec3 n = normalize(cross(dFdx(v_rel), dFdy(v_rel)));
    vec2 dx = dFdx(v_uv), dy = dFdy(v_uv);
    if (v_tex_class >= 0 && !u_false_colour && !u_object_colours) {
        f_color = vec4(texel(dx, dy) * light(n), 1.0);
        return;
    }
    vec3 p = v_rel + u_eye_wrap;
    vec3 w = pow(abs(n), vec3(4.0));
    w /= w.x + w.y + w.z;
    float pattern = w.x * brick(p.yz) + w.y * brick(p.xz) + w.z * brick(p.xy);
    f_color = vec4(mark(v_colour, v_flags) * pattern * light(n), 1.0);
}
