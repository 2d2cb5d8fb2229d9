#version 330 core
// Sky behind everything: a gradient from horizon to zenith, a sun glow and clouds on a plane at
// infinity, all functions of the world-frame view direction only (so their optical flow is the
// rotation-only flow of points at infinity, as the ground truth says).

#if defined VERTEX_SHADER

in vec2 in_position;

void main() { gl_Position = vec4(in_position, 1.0, 1.0); }  // at the far plane

#elif defined FRAGMENT_SHADER

uniform mat3 m_pixel_to_world;  // (u, v, 1) in the rendered image -> world-frame ray direction
uniform vec2 u_origin;          // lower-left corner of this camera's viewport (window pixels)
uniform float u_height;         // viewport height in pixels
uniform vec3 u_sun_dir;
uniform vec3 u_zenith;
uniform vec3 u_horizon;
uniform float u_cloud_cover;
uniform vec2 u_cloud_offset;
uniform vec3 u_cloud_color;  // lit cloud (grey for overcast)
uniform vec3 u_glow_color;   // sun disc and halo (black behind full cloud)

out vec4 fragColor;

uint hash_u(uint x) {
    x ^= x >> 16; x *= 0x7feb352du; x ^= x >> 15; x *= 0x846ca68bu; x ^= x >> 16;
    return x;
}
float hash2(vec2 p) {
    ivec2 i = ivec2(floor(p));
    return float(hash_u(uint(i.x) * 1597334677u ^ hash_u(uint(i.y) + 0x9e3779b9u)) & 0xffffffu) / 16777215.0;
}
float vnoise(vec2 p) {
    vec2 i = floor(p), f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    return mix(mix(hash2(i), hash2(i + vec2(1, 0)), f.x), mix(hash2(i + vec2(0, 1)), hash2(i + vec2(1, 1)), f.x), f.y);
}

void main() {
    // window pixel centres are at +0.5; image rows run top-down
    vec2 pix = vec2(gl_FragCoord.x - u_origin.x - 0.5, u_height - (gl_FragCoord.y - u_origin.y) - 0.5);
    vec3 dir = normalize(m_pixel_to_world * vec3(pix, 1.0));
    float up = clamp(dir.z, 0.0, 1.0);
    vec3 c = mix(u_horizon, u_zenith, pow(up, 0.55));
    float sun = max(dot(dir, u_sun_dir), 0.0);
    c += u_glow_color * (0.25 * pow(sun, 12.0) + 0.6 * pow(sun, 400.0));
    if (dir.z > 0.01) {
        vec2 p = dir.xy / dir.z * 0.6 + u_cloud_offset;
        float fw = length(fwidth(p));
        float n = 0.0, amp = 0.55, freq = 0.35;
        for (int i = 0; i < 4; ++i) {
            n += amp * (1.0 - smoothstep(0.15, 0.5, freq * fw)) * vnoise(p * freq + float(i) * 7.1);
            amp *= 0.5; freq *= 2.3;
        }
        float cloud = smoothstep(1.0 - u_cloud_cover, 1.25 - 0.6 * u_cloud_cover, n + 0.1) * smoothstep(0.01, 0.12, dir.z);
        c = mix(c, u_cloud_color - 0.12 * n, cloud * 0.9);
    }
    fragColor = vec4(c, 1.0);
}

#endif
