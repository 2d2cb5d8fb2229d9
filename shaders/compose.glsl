#version 330 core
// The layered blends (drivingscene.render.scene: "layers", "cameras"). Each layer's splats were
// drawn alone over transparent black (premultiplied colour C_l, accumulated alpha a_l); its
// coverage is k_l = min(1, a_l / u_coverage_full) (render.scene.COVERAGE_FULL). With surface averaging
// (u_surface) the layer came in three targets (shaders/splat.glsl, pass 2): what lies behind the
// front surface composited and attenuated by it (u_layer), the front surface's sum of alpha * rgb
// (u_front_sum) and its (sum alpha, sum -log(1 - alpha)) (u_front_stats): C_l adds A / S times the
// sum, A = 1 - exp(-sum -log(1 - alpha)), S = sum alpha (render.composite).
// u_pass 0 adds one layer with its weight w_l into two accumulation targets (blend ONE, ONE with
// equation ADD for colour and MAX for alpha): acc0 = (sum w_l k_l C_l / a_l, max k_l),
// acc1.r = sum w_l k_l. u_pass 1 resolves them over the sky already in the target (blend
// SRC_ALPHA, ONE_MINUS_SRC_ALPHA): colour acc0.rgb / acc1.r with alpha max k_l (render.scene._compose).

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
uniform sampler2D u_front_sum;
uniform sampler2D u_front_stats;
uniform bool u_surface;
uniform float u_weight;
uniform float u_coverage_full;
in vec2 v_uv;
layout(location = 0) out vec4 out0;
layout(location = 1) out vec4 out1;

void main() {
    if (u_pass == 0) {
        vec4 c = texture(u_layer, v_uv);
        if (u_surface) {
            vec2 stats = texture(u_front_stats, v_uv).rg;
            if (stats.r > 0.0) c.rgb += ((1.0 - exp(-stats.g)) / stats.r) * texture(u_front_sum, v_uv).rgb;
        }
        float coverage = min(1.0, c.a / u_coverage_full);
        out0 = vec4((u_weight / max(c.a, u_coverage_full)) * c.rgb, coverage);
        out1 = vec4(u_weight * coverage, 0.0, 0.0, 0.0);
        return;
    }
    vec4 acc = texture(u_acc0, v_uv);
    float total = texture(u_acc1, v_uv).r;
    vec3 color = total > 1e-12 ? acc.rgb / total : vec3(0.0);
    out0 = vec4(color, acc.a);
    out1 = vec4(0.0);
}

#endif
