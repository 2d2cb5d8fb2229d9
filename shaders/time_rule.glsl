// The time rule of drivingscene/gaussians/timing.py in GLSL (the one definition, also run by the
// torch Gaussians and the viewer's numpy sorter): where a Gaussian is at normalised time t, and its
// opacity weight. Included by splat.glsl and time_rule_probe.glsl (`#include`, drivingscene/gl.py).
// Defines: BLEND_ALL, BLEND_FADE, BLEND_NEAREST, BLEND_LAYER (timing.shader_blend_defines()).

#if !defined BLEND_LAYER
#error "time_rule.glsl needs the BLEND_<NAME> defines of drivingscene.gaussians.timing.shader_blend_defines()"
#endif

// The fraction of its flow a Gaussian of `keyframe` (0.0 or 1.0) has moved at t (timing.time_steps).
float time_step(float keyframe, float t) { return keyframe < 0.5 ? t : 1.0 - t; }

// World position at t of a Gaussian at `mean` on its keyframe, moving by `flow` (timing.means_at).
vec3 mean_at(vec3 mean, float keyframe, vec3 flow, float t) { return mean + time_step(keyframe, t) * flow; }

// Opacity multiplier at t (timing.time_weights; `blend` from timing.shader_blend_code). BLEND_LAYER
// keeps only the Gaussians of keyframe `layer`, fully opaque: one pass of a layered blend.
float time_weight(float keyframe, float t, int blend, int layer) {
    bool k1 = keyframe > 0.5;
    if (blend == BLEND_FADE) return k1 ? t : 1.0 - t;
    if (blend == BLEND_NEAREST) return k1 ? float(t >= 0.5) : float(t < 0.5);
    if (blend == BLEND_LAYER) return float(int(k1) == layer);
    return 1.0;
}
