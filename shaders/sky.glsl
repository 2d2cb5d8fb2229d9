#version 330 core
// The sky background (drivingscene/render/sky.py): colour = max(SH(d) + 0.5, 0) of the world direction d
// through each pixel centre, and below the horizon the ground (with_ground: the road's colour where the ray
// from a camera above the road plane descends, blended in over HORIZON_BAND), drawn as one full-screen
// triangle before the splats (alpha 0).

#if defined VERTEX_SHADER

void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

uniform vec3 u_sky[16];   // SH coefficients (rgb), u_sky_k of them
uniform int u_sky_k;
uniform mat3 u_cam_rot;   // camera-to-world rotation
uniform vec4 u_intr;      // fx, fy, cx, cy
uniform float u_skew;
uniform vec2 u_size;      // W, H
uniform int u_has_ground;
uniform vec4 u_ground;    // road plane n (up), d: n . x + d = 0, in the splats' (origin-relative) frame
uniform vec3 u_ground_rgb;
uniform vec3 u_cam_pos;   // camera centre, same frame
uniform float u_horizon_band;
out vec4 fragColor;

const float SH_C0 = 0.28209479177387814;
const float SH_C1 = 0.4886025119029199;

vec3 eval_sh(vec3 d) {
    vec3 result = SH_C0 * u_sky[0];
    if (u_sky_k < 4) return result;
    float x = d.x, y = d.y, z = d.z;
    result += SH_C1 * (-y * u_sky[1] + z * u_sky[2] - x * u_sky[3]);
    if (u_sky_k < 9) return result;
    float xx = x * x, yy = y * y, zz = z * z;
    result += 1.0925484305920792 * x * y * u_sky[4] - 1.0925484305920792 * y * z * u_sky[5]
            + 0.31539156525252005 * (2.0 * zz - xx - yy) * u_sky[6] - 1.0925484305920792 * x * z * u_sky[7]
            + 0.5462742152960396 * (xx - yy) * u_sky[8];
    if (u_sky_k < 16) return result;
    result += -0.5900435899266435 * y * (3.0 * xx - yy) * u_sky[9] + 2.890611442640554 * x * y * z * u_sky[10]
            - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * u_sky[11]
            + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * u_sky[12]
            - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * u_sky[13] + 1.445305721320277 * z * (xx - yy) * u_sky[14]
            - 0.5900435899266435 * x * (xx - 3.0 * yy) * u_sky[15];
    return result;
}

void main() {
    // gl_FragCoord is (u + 0.5, H - v - 0.5) for the pixel centred at (u, v).
    float u = gl_FragCoord.x - 0.5;
    float v = u_size.y - gl_FragCoord.y - 0.5;
    float y = (v - u_intr.w) / u_intr.y;
    float x = (u - u_intr.z - u_skew * y) / u_intr.x;
    vec3 d = normalize(u_cam_rot * vec3(x, y, 1.0));
    vec3 color = max(eval_sh(d) + 0.5, 0.0);
    if (u_has_ground == 1 && dot(u_ground.xyz, u_cam_pos) + u_ground.w > 0.0) {
        float w = clamp(-dot(d, u_ground.xyz) / u_horizon_band, 0.0, 1.0);
        color += w * (u_ground_rgb - color);
    }
    fragColor = vec4(color, 0.0);
}

#endif
