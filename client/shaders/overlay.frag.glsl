#version 330 core
// The overlay's pixels, straight (not premultiplied) alpha: blended with SRC_ALPHA, ONE_MINUS_SRC_ALPHA.

uniform sampler2D u_overlay;
in vec2 v_uv;
out vec4 f_colour;

void main() {
    f_colour = texture(u_overlay, v_uv);
}
