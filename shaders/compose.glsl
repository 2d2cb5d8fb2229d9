#version 330 core
// The "layers" blend (drivingscene.render.scene.render_layers): each keyframe's splats were drawn
// alone over the sky into their own target; per pixel the two pictures are blended with weights
// (1 - t + floor) alpha_0 and (t + floor) alpha_1 (both 0.5 where neither layer has a splat).

#if defined VERTEX_SHADER

out vec2 v_uv;

void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    v_uv = p;
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

uniform sampler2D u_layer0;
uniform sampler2D u_layer1;
uniform float u_t;
uniform float u_floor;
in vec2 v_uv;
out vec4 fragColor;

void main() {
    vec4 a = texture(u_layer0, v_uv);
    vec4 b = texture(u_layer1, v_uv);
    float w0 = (1.0 - u_t + u_floor) * a.a;
    float w1 = (u_t + u_floor) * b.a;
    if (w0 + w1 < 1e-6) {
        w0 = 0.5;
        w1 = 0.5;
    }
    fragColor = vec4((w0 * a.rgb + w1 * b.rgb) / (w0 + w1), max(a.a, b.a));
}

#endif
