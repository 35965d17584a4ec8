#version 330 core
// The sky pass (client.sky): one triangle that covers the viewport, made from
// gl_VertexID, no vertex buffer. Each pixel's view direction comes from the
// inverse of the camera-relative view-projection (the eye is at the origin).

uniform mat4 u_inverse_view_projection;

out vec3 v_direction;

void main() {
    vec2 ndc = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2)) * 2.0 - 1.0;
    vec4 far = u_inverse_view_projection * vec4(ndc, 1.0, 1.0);
    v_direction = far.xyz / far.w;
    gl_Position = vec4(ndc, 1.0, 1.0);
}
