#version 330 core
// The layered blends (drivingscene.render.scene: "layers", "cameras"). Each layer's splats were
// drawn alone over transparent black (premultiplied colour C_l, accumulated alpha a_l); its
// coverage is k_l = min(1, a_l / u_coverage_full) (render.scene.COVERAGE_FULL). With surface averaging
// (u_surface) the layer came in three targets (shaders/splat.glsl, pass 2): what lies behind the
// front surface composited and attenuated by it (u_layer), the front surface's sum of alpha * rgb
// (u_front_sum) and its (sum alpha, sum -log(1 - alpha)) (u_front_stats): C_l adds A / S times the
// sum, A = 1 - exp(-sum -log(1 - alpha)), S = sum alpha (render.composite).
// u_pass 0 adds one layer of keyframe u_keyframe with its view weight w_l into four accumulation
// targets (blend ONE, ONE with equation ADD for colour and MAX for alpha), one per keyframe for its
// layers' colour and two for the weights: acc0 (keyframe 0) and acc2 (keyframe 1) =
// (sum w_l k_l C_l / a_l, max k_l), acc1 = (sum w_l k_l of keyframe 0, of keyframe 1, 0,
// max w_l k_l of keyframe 0), acc3.a = max w_l k_l of keyframe 1. u_pass 1 resolves them over the
// sky already in the target (blend SRC_ALPHA, ONE_MINUS_SRC_ALPHA): each keyframe's colour
// acc.rgb / sum, mixed with the weights of render.scene.keyframe_weights at time u_time from the
// sums T_k = sum w_l k_l, coverages A_k = max k_l and views V_k = max w_l k_l, alpha max A_k
// (render.scene._compose).

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
uniform sampler2D u_acc2;
uniform sampler2D u_acc3;
uniform float u_far_mix;
uniform sampler2D u_front_sum;
uniform sampler2D u_front_stats;
uniform bool u_surface;
uniform float u_weight;
uniform int u_keyframe;
uniform float u_time;
uniform float u_coverage_full;
in vec2 v_uv;
layout(location = 0) out vec4 out0;
layout(location = 1) out vec4 out1;
layout(location = 2) out vec4 out2;
layout(location = 3) out vec4 out3;

void main() {
    if (u_pass == 0) {
        vec4 c = texture(u_layer, v_uv);
        if (u_surface) {
            vec2 stats = texture(u_front_stats, v_uv).rg;
            if (stats.r > 0.0) c.rgb += ((1.0 - exp(-stats.g)) / stats.r) * texture(u_front_sum, v_uv).rgb;
        }
        float coverage = min(1.0, c.a / u_coverage_full);
        vec4 layer = vec4((u_weight / max(c.a, u_coverage_full)) * c.rgb, coverage);
        bool first = u_keyframe == 0;
        out0 = first ? layer : vec4(0.0);
        out2 = first ? vec4(0.0) : layer;
        float w = u_weight * coverage;
        out1 = first ? vec4(w, 0.0, 0.0, w) : vec4(0.0, w, 0.0, 0.0);
        out3 = vec4(0.0, 0.0, 0.0, first ? 0.0 : w);
        return;
    }
    vec4 key0 = texture(u_acc0, v_uv);
    vec4 key1 = texture(u_acc2, v_uv);
    vec2 totals = texture(u_acc1, v_uv).rg;
    vec3 color0 = totals.r > 1e-12 ? key0.rgb / totals.r : vec3(0.0);
    vec3 color1 = totals.g > 1e-12 ? key1.rgb / totals.g : vec3(0.0);
    float view0 = texture(u_acc1, v_uv).a;
    float view1 = texture(u_acc3, v_uv).a;
    float s = abs(1.0 - 2.0 * u_time);
    float w0 = (s * key0.a + (1.0 - s) * totals.r) * (1.0 - u_time * key1.a + u_far_mix * s * (1.0 - view1));
    float w1 = (s * key1.a + (1.0 - s) * totals.g) * (1.0 - (1.0 - u_time) * key0.a + u_far_mix * s * (1.0 - view0));
    float total = w0 + w1;
    vec3 color = total > 1e-12 ? (w0 * color0 + w1 * color1) / total : vec3(0.0);
    out0 = vec4(color, max(key0.a, key1.a));
    out1 = vec4(0.0);
    out2 = vec4(0.0);
    out3 = vec4(0.0);
}

#endif
