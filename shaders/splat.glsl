#version 330 core
// 3D Gaussian splats as vertex-id quads (6 vertices per splat, no vertex buffers), drawn back to front.
// Same model as drivingscene/render (project.py, composite.py, sh.py): Σ = R S Sᵀ Rᵀ, EWA 2D covariance
// J W Σ Wᵀ Jᵀ + eps2d I with J clamped off-image as 3DGS, alpha = min(0.99, o exp(-½ dᵀΣ2D⁻¹d)), cut at
// the 3-sigma ellipse and alpha < 1/255, colour max(SH(d) + 0.5, 0) with d from the camera centre.
// Pixel (u, v) has its centre at integer coordinates (OpenCV); image row 0 is the top of the viewport.
// u_surface_pass (drivingscene/render/composite.py, surface averaging; app/renderer.py draws the passes):
// 0 plain: (rgb, alpha) for back-to-front "over" blending. 1: the splat's camera z, blended with MIN
// into a front-depth target (the pixel's front-most splat that passes the cut). 2: with premultiplied
// blending (ONE, ONE_MINUS_SRC_ALPHA) into three targets: a splat within u_tolerance of the front
// depth adds alpha * rgb to out1 and (alpha, -log(1 - alpha)) to out2 (alpha 0: plain sums) and
// attenuates out0; one behind it is composited into out0 as in pass 0.
// Defines: TEX_W (width of the data textures), BLEND_<NAME> (drivingscene.gaussians.timing.shader_blend_defines).

#if defined VERTEX_SHADER

uniform sampler2D u_pos;      // RGBA32F [i]: mean xyz (origin-relative, at its keyframe), keyframe
uniform sampler2D u_motion;   // RGBA32F [i]: flow xyz, opacity
uniform sampler2D u_cov_a;    // RGBA32F [i]: Σxx Σxy Σxz Σyy
uniform sampler2D u_cov_b;    // RGBA32F [i]: Σyz Σzz |flow| 0
uniform sampler2D u_sh;       // RGBA32F [i * K + k]: SH coefficient k (rgb)
uniform usampler2D u_flags;   // R8UI [i]: bit 0 hidden, bit 1 selected
uniform usampler2D u_order;   // R32UI [j]: Gaussian index of the j-th splat front to back
uniform sampler2D u_view_ray; // RGBA32F [i]: view ray xyz of a view-bound Gaussian (zero: not view-bound)
uniform vec2 u_view_fade;     // cosines (gaussians.core.view_fade): full opacity at or above x, none at or below y
uniform sampler2D u_lut;      // 256 x 1 colour map for the flow-magnitude mode

uniform int u_count;          // splats in u_order
uniform int u_sh_k;           // SH coefficients per channel (1, 4, 9, 16)
uniform mat4 u_view;          // world (origin-relative) to camera, OpenCV axes
uniform vec3 u_cam_centre;    // camera centre, origin-relative world
uniform vec4 u_intr;          // fx, fy, cx, cy (pixels)
uniform float u_skew;
uniform vec2 u_size;          // W, H (pixels)
uniform float u_t;            // normalised time
uniform int u_blend;          // BLEND_<NAME>: time_weight in time_rule.glsl (timing.shader_blend_code)
uniform int u_layer;          // the keyframe drawn when u_blend is BLEND_LAYER (renderer.py composes the layers)
uniform int u_mode;           // 0 rgb, 1 depth, 2 dynamic highlight, 3 flow magnitude
uniform float u_flow_max;     // metres at the top of the colour map
uniform bool u_show_selection;
uniform float u_near;
uniform float u_far;
uniform float u_eps2d;

noperspective out vec2 v_offset;
flat out float v_z;               // camera z of the splat's centre  // pixel centre minus the splat's 2D mean (pixels)
flat out vec3 v_conic;            // (a, b, c) of Σ2D⁻¹
flat out vec4 v_color;            // rgb (depth mode: camera z), opacity
flat out float v_sigma_max;

const float SH_C0 = 0.28209479177387814;
const float SH_C1 = 0.4886025119029199;

ivec2 texel(int i) { return ivec2(i % TEX_W, i / TEX_W); }

vec3 sh_coeff(int gid, int k) { return texelFetch(u_sh, texel(gid * u_sh_k + k), 0).rgb; }

// Real SH with the constants and signs of 3DGS (drivingscene/render/sh.py); dir need not be unit.
vec3 eval_sh(int gid, vec3 dir) {
    vec3 result = SH_C0 * sh_coeff(gid, 0);
    if (u_sh_k < 4) return result;
    vec3 d = normalize(dir);
    float x = d.x, y = d.y, z = d.z;
    result += SH_C1 * (-y * sh_coeff(gid, 1) + z * sh_coeff(gid, 2) - x * sh_coeff(gid, 3));
    if (u_sh_k < 9) return result;
    float xx = x * x, yy = y * y, zz = z * z;
    result += 1.0925484305920792 * x * y * sh_coeff(gid, 4)
            - 1.0925484305920792 * y * z * sh_coeff(gid, 5)
            + 0.31539156525252005 * (2.0 * zz - xx - yy) * sh_coeff(gid, 6)
            - 1.0925484305920792 * x * z * sh_coeff(gid, 7)
            + 0.5462742152960396 * (xx - yy) * sh_coeff(gid, 8);
    if (u_sh_k < 16) return result;
    result += -0.5900435899266435 * y * (3.0 * xx - yy) * sh_coeff(gid, 9)
            + 2.890611442640554 * x * y * z * sh_coeff(gid, 10)
            - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * sh_coeff(gid, 11)
            + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh_coeff(gid, 12)
            - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * sh_coeff(gid, 13)
            + 1.445305721320277 * z * (xx - yy) * sh_coeff(gid, 14)
            - 0.5900435899266435 * x * (xx - 3.0 * yy) * sh_coeff(gid, 15);
    return result;
}

#include "time_rule.glsl"

vec3 splat_color(int gid, vec3 mean, float z, float flow_mag, bool selected) {
    vec3 rgb;
    if (u_mode == 1) return vec3(z);
    if (u_mode == 3) {
        rgb = texture(u_lut, vec2(clamp(flow_mag / u_flow_max, 0.0, 1.0) * (255.0 / 256.0) + 0.5 / 256.0, 0.5)).rgb;
    } else {
        rgb = max(eval_sh(gid, mean - u_cam_centre) + 0.5, 0.0);
        if (u_mode == 2) {
            float grey = dot(min(rgb, 1.0), vec3(0.299, 0.587, 0.114));
            rgb = flow_mag > 0.0 ? mix(rgb, vec3(1.0, 0.45, 0.05), 0.65) : vec3(0.25 + 0.45 * grey);
        }
    }
    if (selected && u_show_selection) rgb = mix(rgb, vec3(1.0, 0.2, 0.85), 0.6);  // magenta: apart from every colour map
    return rgb;
}

void cull() { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); v_color = vec4(0.0); v_sigma_max = -1.0; v_z = 0.0; }

void main() {
#if defined INDEXED
    int splat = gl_VertexID >> 2;  // indexed draw: the index is 4 * splat + corner (vertex cache reuse)
    int corner = gl_VertexID & 3;
#else
    int splat = gl_VertexID / 6;
    int corner = gl_VertexID - 6 * splat;
#endif
    if (splat >= u_count) { cull(); return; }
    int gid = int(texelFetch(u_order, texel(u_count - 1 - splat), 0).r);  // back to front
    uint flags = texelFetch(u_flags, texel(gid), 0).r;
    vec4 pos = texelFetch(u_pos, texel(gid), 0);
    vec4 motion = texelFetch(u_motion, texel(gid), 0);
    float opacity = motion.w * time_weight(pos.w, u_t, u_blend, u_layer);
    if ((flags & 1u) != 0u || opacity < 1.0 / 255.0) { cull(); return; }
    vec3 mean = mean_at(pos.xyz, pos.w, motion.xyz, u_t);
    vec3 view_ray = texelFetch(u_view_ray, texel(gid), 0).xyz;
    if (view_ray != vec3(0.0)) {  // view-bound: faded with the angle between the view ray and its own
        float cosine = dot(normalize(mean - u_cam_centre), view_ray);
        opacity *= clamp((cosine - u_view_fade.y) / (u_view_fade.x - u_view_fade.y), 0.0, 1.0);
        if (opacity < 1.0 / 255.0) { cull(); return; }
    }
    vec3 p = (u_view * vec4(mean, 1.0)).xyz;
    if (p.z < u_near || p.z > u_far) { cull(); return; }

    // EWA projection (Zwicker et al. 2002), Jacobian at x/z, y/z clamped to the image + 30% half-FOV.
    float fx = u_intr.x, fy = u_intr.y, cx = u_intr.z, cy = u_intr.w;
    float inv_z = 1.0 / p.z;
    vec2 mean2d = vec2(fx * p.x * inv_z + u_skew * p.y * inv_z + cx, fy * p.y * inv_z + cy);
    float mx = 0.15 * u_size.x / fx, my = 0.15 * u_size.y / fy;
    float tx = clamp(p.x * inv_z, -(cx + 0.5) / fx - mx, (u_size.x - 0.5 - cx) / fx + mx);
    float ty = clamp(p.y * inv_z, -(cy + 0.5) / fy - my, (u_size.y - 0.5 - cy) / fy + my);
    mat3 rot = mat3(u_view);  // columns of the world-to-camera rotation
    vec3 t0 = (fx * inv_z) * vec3(rot[0].x, rot[1].x, rot[2].x) + (u_skew * inv_z) * vec3(rot[0].y, rot[1].y, rot[2].y)
            - ((fx * tx + u_skew * ty) * inv_z) * vec3(rot[0].z, rot[1].z, rot[2].z);
    vec3 t1 = (fy * inv_z) * vec3(rot[0].y, rot[1].y, rot[2].y) - (fy * ty * inv_z) * vec3(rot[0].z, rot[1].z, rot[2].z);
    vec4 ca = texelFetch(u_cov_a, texel(gid), 0);
    vec4 cb = texelFetch(u_cov_b, texel(gid), 0);
    mat3 cov = mat3(ca.x, ca.y, ca.z, ca.y, ca.w, cb.x, ca.z, cb.x, cb.y);
    vec3 cov_t0 = cov * t0;
    float a = dot(t0, cov_t0) + u_eps2d;
    float b = dot(t1, cov_t0);
    float c = dot(t1, cov * t1) + u_eps2d;
    float det = a * c - b * b;
    float sigma_max = min(4.5, log(255.0 * opacity));  // 3-sigma ellipse and alpha >= 1/255
    if (det <= 0.0 || sigma_max <= 0.0) { cull(); return; }

    // Smallest rectangle around {d : dᵀ Σ2D⁻¹ d <= 2 sigma_max}: the ellipse's own axes.
    float mid = 0.5 * (a + c);
    float disc = sqrt(max(mid * mid - det, 0.0));
    float l1 = mid + disc, l2 = max(mid - disc, 0.0);
    vec2 e1 = abs(b) > 1e-9 * (a + c) ? normalize(vec2(b, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    vec2 e2 = vec2(-e1.y, e1.x);
    float grow = 1.0 + 1e-3;
    vec2 r = sqrt(2.0 * sigma_max * vec2(l1, l2)) * grow + 1e-3;
#if defined INDEXED
    const vec2 corners[4] = vec2[4](vec2(-1, -1), vec2(1, -1), vec2(-1, 1), vec2(1, 1));
#else
    const vec2 corners[6] = vec2[6](vec2(-1, -1), vec2(1, -1), vec2(-1, 1), vec2(-1, 1), vec2(1, -1), vec2(1, 1));
#endif
    vec2 offset = corners[corner].x * r.x * e1 + corners[corner].y * r.y * e2;
    vec2 pixel = mean2d + offset;
    gl_Position = vec4(2.0 * (pixel.x + 0.5) / u_size.x - 1.0, 1.0 - 2.0 * (pixel.y + 0.5) / u_size.y, 0.0, 1.0);
    v_offset = offset;
    v_conic = vec3(c, -b, a) / det;
    v_sigma_max = sigma_max;
    v_z = p.z;
    v_color = vec4(splat_color(gid, mean, p.z, cb.z, (flags & 2u) != 0u), opacity);
}

#elif defined FRAGMENT_SHADER

uniform int u_surface_pass;
uniform sampler2D u_front;     // pass 2: the front depth of pass 1
uniform float u_tolerance;     // relative depth of the front surface

noperspective in vec2 v_offset;
flat in vec3 v_conic;
flat in vec4 v_color;
flat in float v_sigma_max;
flat in float v_z;
layout(location = 0) out vec4 out0;
layout(location = 1) out vec4 out1;
layout(location = 2) out vec4 out2;

void main() {
    vec2 d = -v_offset;  // the mean relative to the pixel centre; sigma is even in d
    float sigma = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
    if (sigma > v_sigma_max) discard;
    float alpha = min(0.99, v_color.a * exp(-sigma));
    if (alpha < 1.0 / 255.0) discard;
    out1 = vec4(0.0);
    out2 = vec4(0.0);
    if (u_surface_pass == 0) {
        out0 = vec4(v_color.rgb, alpha);
    } else if (u_surface_pass == 1) {
        out0 = vec4(v_z, 0.0, 0.0, 0.0);
    } else if (v_z <= texelFetch(u_front, ivec2(gl_FragCoord.xy), 0).r * (1.0 + u_tolerance)) {
        out0 = vec4(0.0, 0.0, 0.0, alpha);
        out1 = vec4(alpha * v_color.rgb, 0.0);
        out2 = vec4(alpha, -log(1.0 - alpha), 0.0, 0.0);
    } else {
        out0 = vec4(alpha * v_color.rgb, alpha);
    }
}

#endif
