#version 330 core
// The kiosk overlay (client/kiosk/compositor.py): one full-frame quad, drawn as a strip of four vertices
// made from gl_VertexID, so no vertex buffer is needed.

out vec2 v_uv;

void main() {
    vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1));
    // The overlay image's rows are top-down (Pillow); the framebuffer's are bottom-up.
    v_uv = vec2(corner.x, 1.0 - corner.y);
    gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);
}
