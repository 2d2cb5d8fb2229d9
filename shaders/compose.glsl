#version 330 core
// The layered blends (drivingscene.render.scene: "layers", "cameras"). Each layer's splats were
// drawn alone over transparent black (premultiplied colour C_l, coverage a_l).
// u_pass 0 adds one layer with its weight w_l into two accumulation targets (blend ONE, ONE with
// equation ADD for colour and MAX for alpha): acc0 = (sum w_l C_l, max a_l), acc1.r = sum w_l a_l.
// u_pass 1 resolves them over the sky already in the target (blend SRC_ALPHA, ONE_MINUS_SRC_ALPHA):
// colour sum w_l C_l / sum w_l a_l with alpha max a_l (render.scene._compose).

#if defined VERTEX_SHADER

out vec2 v_uv;

void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    v_uv = p;
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

uniform int u_pass;
uniform sampler2D u_layer;
uniform sampler2D u_acc0;
uniform sampler2D u_acc1;
uniform float u_weight;
in vec2 v_uv;
layout(location = 0) out vec4 out0;
layout(location = 1) out vec4 out1;

void main() {
    if (u_pass == 0) {
        vec4 c = texture(u_layer, v_uv);
        out0 = vec4(u_weight * c.rgb, c.a);
        out1 = vec4(u_weight * c.a, 0.0, 0.0, 0.0);
        return;
    }
    vec4 acc = texture(u_acc0, v_uv);
    float total = texture(u_acc1, v_uv).r;
    vec3 color = total > 1e-12 ? acc.rgb / total : vec3(0.0);
    out0 = vec4(color, acc.a);
    out1 = vec4(0.0);
}

#endif
