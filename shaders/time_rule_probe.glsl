#version 330 core
// The time rule (time_rule.glsl, the functions splat.glsl runs) evaluated per vertex into
// transform-feedback varyings, so that tests compare the GLSL with drivingscene/gaussians/timing.py.
// Defines: BLEND_<NAME> (timing.shader_blend_defines()).

#if defined VERTEX_SHADER

#include "time_rule.glsl"

uniform float u_t;      // normalised time
uniform int u_blend;    // BLEND_<NAME>
uniform int u_layer;    // the keyframe kept by BLEND_LAYER

in vec3 in_mean;        // at its keyframe
in vec3 in_flow;
in float in_keyframe;   // 0.0 or 1.0, as splat.glsl reads it from u_pos.w

out vec3 out_mean;
out float out_step;
out float out_weight;

void main() {
    out_mean = mean_at(in_mean, in_keyframe, in_flow, u_t);
    out_step = time_step(in_keyframe, u_t);
    out_weight = time_weight(in_keyframe, u_t, u_blend, u_layer);
}

#endif
