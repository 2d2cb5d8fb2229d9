#version 330 core
// Colour pass of the synthetic town: procedural textures in object coordinates (so they move with
// their objects), sun + sky Lambert shading, distance haze. Material ids arrive as MAT_* defines
// from drivingscene/synth/meshes.py, and each program is compiled for one MATERIAL. Texture detail
// is band-limited by the pixel footprint so supersampling does not alias it into flicker.

#if defined VERTEX_SHADER

uniform mat4 m_proj;            // camera -> clip (OpenCV camera axes, pixel centres at integers)
uniform mat4 m_model_to_cam;
uniform mat4 m_model_to_world;

in vec3 in_position;
in vec3 in_normal;
in vec2 in_uv;
in vec3 in_color;
in float in_param;
in vec2 in_extra;

out vec3 v_obj;
out vec3 v_normal_obj;
out vec3 v_world;
out vec3 v_normal;
out vec2 v_uv;
out vec3 v_cam;  // camera-frame position: affine, so exact when interpolated (a distance is not)
flat out vec3 v_color;
flat out float v_param;
flat out vec2 v_extra;

void main() {
    vec4 cam = m_model_to_cam * vec4(in_position, 1.0);
    gl_Position = m_proj * cam;
    v_obj = in_position;
    v_normal_obj = in_normal;
    v_world = (m_model_to_world * vec4(in_position, 1.0)).xyz;
    v_normal = mat3(m_model_to_world) * in_normal;
    v_uv = in_uv;
    v_cam = cam.xyz;
    v_color = in_color;
    v_param = in_param;
    v_extra = in_extra;
}

#elif defined FRAGMENT_SHADER

uniform vec3 u_sun_dir;
uniform vec3 u_sun_color;
uniform vec3 u_ambient;
uniform vec3 u_haze_color;
uniform float u_haze_distance;
uniform vec3 u_cam_pos;
uniform float u_texture;
uniform float u_ground_z;
uniform float u_band_scale;

in vec3 v_obj;
in vec3 v_normal_obj;
in vec3 v_world;
in vec3 v_normal;
in vec2 v_uv;
in vec3 v_cam;
flat in vec3 v_color;
flat in float v_param;
flat in vec2 v_extra;

out vec4 fragColor;

// Integer hashes of lattice points: the coordinates combined, then one lowbias32 finaliser.
uint mix32(uint h) {
    h ^= h >> 16; h *= 0x7feb352du; h ^= h >> 15; h *= 0x846ca68bu; h ^= h >> 16;
    return h;
}
float hash2(vec2 p) {
    ivec2 i = ivec2(floor(p));
    return float(mix32(uint(i.x) * 0x27d4eb2du + uint(i.y) * 0x165667b1u) & 0xffffffu) / 16777215.0;
}
float hash3(vec3 p) {
    ivec3 i = ivec3(floor(p));
    return float(mix32(uint(i.x) * 0x27d4eb2du + uint(i.y) * 0x165667b1u + uint(i.z) * 0x9e3779b1u) & 0xffffffu)
           / 16777215.0;
}
float vnoise(vec2 p) {  // value noise in [-1, 1]
    vec2 i = floor(p), f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    float a = hash2(i), b = hash2(i + vec2(1, 0)), c = hash2(i + vec2(0, 1)), d = hash2(i + vec2(1, 1));
    return 2.0 * mix(mix(a, b, f.x), mix(c, d, f.x), f.y) - 1.0;
}
float vnoise3(vec3 p) {
    vec3 i = floor(p), f = fract(p);
    f = f * f * (3.0 - 2.0 * f);
    float a = mix(mix(hash3(i), hash3(i + vec3(1, 0, 0)), f.x), mix(hash3(i + vec3(0, 1, 0)), hash3(i + vec3(1, 1, 0)), f.x), f.y);
    float b = mix(mix(hash3(i + vec3(0, 0, 1)), hash3(i + vec3(1, 0, 1)), f.x),
                  mix(hash3(i + vec3(0, 1, 1)), hash3(i + vec3(1, 1, 1)), f.x), f.y);
    return 2.0 * mix(a, b, f.z) - 1.0;
}
// Weight of a pattern of spatial frequency `freq` (cycles per metre) given the footprint `fw` (metres
// per rendered sample): patterns finer than about 1.5 output pixels (u_band_scale = supersampling
// factor) fade out, so the box filter is not left to alias them differently in every frame.
float band(float freq, float fw) { return 1.0 - smoothstep(0.3, 0.7, freq * fw * u_band_scale); }
// footprint of a sample in the units of p: geometric mean of the two screen axes (grazing views keep
// detail across the line of sight)
float footprint2(vec2 p) { return sqrt(max(length(dFdx(p)) * length(dFdy(p)), 1e-12)); }
float footprint3(vec3 p) { return sqrt(max(length(dFdx(p)) * length(dFdy(p)), 1e-12)); }
float fbm2(vec2 p, float freq, float fw) {  // three octaves, band-limited
    float s = 0.0, amp = 0.5;
    for (int i = 0; i < 3; ++i) {
        s += amp * band(freq, fw) * vnoise(p * freq + float(i) * 17.3);
        freq *= 2.7; amp *= 0.55;
    }
    return s;
}
// anti-aliased 0/1 mask of |x| < half_width
float aa_band(float x, float half_width, float fw) { return 1.0 - smoothstep(half_width - fw, half_width + fw, abs(x)); }
// anti-aliased grid lines of `width` every `period`
float grid_line(float x, float period, float width, float fw) {
    float d = abs(fract(x / period + 0.5) - 0.5) * period;
    return (1.0 - smoothstep(width * 0.5 - fw, width * 0.5 + fw, d)) * band(1.0 / max(width, 1e-3), fw * 0.5);
}

vec3 asphalt(vec2 uv, float fw) {
    float n = 0.6 * fbm2(uv, 0.15, fw) + 0.55 * fbm2(uv + 31.0, 0.8, fw) + 0.4 * vnoise(uv * 5.0) * band(5.0, fw);
    float patch_ = smoothstep(0.3, 0.42, vnoise(uv * vec2(0.07, 0.25) + 5.0)) * 0.16;
    float stain = smoothstep(0.55, 0.75, vnoise(uv * 0.6 + 13.0)) * 0.18 * band(0.6, fw);
    // darker wheel tracks along the lanes (uv.y is the lateral offset d)
    float lane = fract(uv.y / 3.4 + 0.5);
    float tracks = (aa_band(lane - 0.28, 0.07, fw) + aa_band(lane - 0.72, 0.07, fw)) * 0.08 * band(3.0, fw);
    return v_color * (1.0 + u_texture * (0.32 * n - patch_ - stain - tracks));
}
vec3 sidewalk(vec2 uv, float fw) {
    vec2 tile = floor(uv / 0.6);
    float joints = max(grid_line(uv.x, 0.6, 0.025, fw), grid_line(uv.y, 0.6, 0.025, fw));
    float t = (hash2(tile + 7.0) - 0.5) * 0.3 * band(1.0 / 0.6, fw) + 0.3 * fbm2(uv, 0.5, fw);
    return v_color * (1.0 + u_texture * t) * (1.0 - 0.4 * u_texture * joints);
}
vec3 kerb(vec2 uv, float fw) {
    float joints = grid_line(uv.x, 1.0, 0.02, fw);
    float t = (hash2(vec2(floor(uv.x), 3.0)) - 0.5) * 0.16 + 0.2 * fbm2(uv, 2.0, fw);
    return v_color * (1.0 + u_texture * t) * (1.0 - 0.3 * u_texture * joints);
}

// Ground floor: shop windows with mullions and a dark interior, a door, a fascia band and a plinth.
vec3 shopfront(vec3 wall, vec2 uv, float fw, float spacing, float ground_h, float cols, inout float gloss) {
    float bay_w = spacing * 2.0;
    float bay = floor(uv.x / bay_w);
    float bx = (fract(uv.x / bay_w) - 0.5) * bay_w;
    float id = hash2(vec2(bay, v_param * 61.0));
    float in_front = aa_band(uv.x, cols * spacing * 0.5, fw);
    float top = ground_h - 0.9;
    float door = step(0.75, id);
    float z0 = mix(0.55, 0.0, door), x_half = mix(bay_w * 0.38, 0.55, door);
    float glass = aa_band(bx, x_half, fw) * aa_band(uv.y - 0.5 * (z0 + top), 0.5 * (top - z0), fw) * in_front;
    float mullions = max(grid_line(bx, 1.1, 0.06, fw) * (1.0 - door), aa_band(uv.y - (top - 0.55), 0.03, fw));
    float frame = aa_band(bx, x_half + 0.08, fw) * aa_band(uv.y - 0.5 * (z0 + top), 0.5 * (top - z0) + 0.08, fw) * in_front;
    vec3 interior = mix(vec3(0.07, 0.075, 0.08), vec3(0.32, 0.28, 0.24), hash2(vec2(bay, 5.0 + v_param * 17.0)));
    interior *= 0.7 + 0.3 * smoothstep(z0, top, uv.y) + 0.25 * u_texture * vnoise(uv * 1.7 + id * 40.0) * band(1.7, fw);
    vec3 frame_c = mix(vec3(0.12, 0.12, 0.13), vec3(0.75, 0.74, 0.7), step(0.5, fract(v_param * 3.7)));
    vec3 sign = vec3(hash2(vec2(bay, 11.0 + v_param * 97.0)), hash2(vec2(bay + 0.5 * v_param, 23.0)), hash2(vec2(bay, 37.0 - v_param * 51.0)));
    vec3 fascia = mix(wall * 0.5, mix(vec3(0.3), sign, 0.55), 0.7);
    vec3 c = mix(wall, wall * 0.6, aa_band(uv.y, 0.4, fw));  // plinth
    c = mix(c, fascia, aa_band(uv.y - (ground_h - 0.5), 0.3, fw) * in_front * step(0.35, fract(v_param * 5.3)));
    c = mix(c, frame_c, frame);
    c = mix(c, mix(interior, frame_c, mullions), glass);
    gloss = max(gloss, glass * (1.0 - mullions));
    return c;
}

// Façades: uv = (metres from the face centre, height); v_extra = (face half width, building height).
vec3 windows(vec3 wall, vec2 uv, float fw, inout float gloss) {
    float h1 = fract(v_param * 7.31), h2 = fract(v_param * 13.7), h3 = fract(v_param * 29.1);
    float floor_h = 3.0 + 0.6 * h1, ground_h = floor_h + 0.9;
    float spacing = 2.2 + 1.3 * h2, win_w = spacing * (0.4 + 0.22 * h3), win_h = floor_h * (0.45 + 0.15 * h1);
    float cols = floor((2.0 * v_extra.x - 1.4) / spacing);
    if (cols < 1.0) return wall;
    float fx = uv.x / spacing + 0.5 * mod(cols, 2.0);
    float dx = (fract(fx) - 0.5) * spacing;
    float inside_x = aa_band(uv.x, cols * spacing * 0.5, fw);
    vec3 c = wall;
    if (uv.y > ground_h) {
        float k = floor((uv.y - ground_h) / floor_h);
        float dz = uv.y - ground_h - k * floor_h - floor_h * 0.52;
        float fits = step(ground_h + (k + 1.0) * floor_h, v_extra.y - 0.2);
        float frame = aa_band(dx, win_w * 0.5 + 0.09, fw) * aa_band(dz, win_h * 0.5 + 0.09, fw) * inside_x * fits;
        float glass = aa_band(dx, win_w * 0.5, fw) * aa_band(dz, win_h * 0.5, fw) * inside_x * fits;
        float id = hash2(vec2(floor(fx), k) + v_param * 100.0);
        vec3 tint = mix(vec3(0.10, 0.13, 0.17), vec3(0.42, 0.52, 0.62), id * 0.8 + 0.2 * clamp(dz / win_h + 0.5, 0.0, 1.0));
        tint = mix(tint, vec3(0.75, 0.68, 0.55), step(0.85, id) * step(0.0, dz));  // curtains
        float sill = aa_band(dz + win_h * 0.5 + 0.12, 0.06, fw) * aa_band(dx, win_w * 0.5 + 0.15, fw) * inside_x * fits;
        c = mix(c, vec3(0.88, 0.87, 0.84), max(frame, sill) * (0.6 + 0.4 * h3));
        c = mix(c, tint, glass);
        gloss = max(gloss, glass);
        float course = aa_band(uv.y - ground_h - k * floor_h, 0.12, fw);
        c = mix(c, wall * 0.82, course * step(0.5, h2));
    } else {
        c = shopfront(wall, uv, fw, spacing, ground_h, cols, gloss);
    }
    return c;
}

vec3 facade(vec2 uv, float fw, inout float gloss) {
    vec3 wall = v_color;
    float t = u_texture;
#if MATERIAL == MAT_plaster
    {
        wall *= 1.0 + t * (0.24 * fbm2(uv, 0.3, fw) + 0.08 * vnoise(uv * vec2(2.5, 0.5)) * band(2.5, fw)
                           - 0.12 * smoothstep(1.2, 0.0, uv.y) * (0.6 + 0.4 * vnoise(uv * 1.3)));  // grime
    }
#elif MATERIAL == MAT_brick
    {
        float row = floor(uv.y / 0.075);
        vec2 brick = vec2(floor(uv.x / 0.24 + 0.5 * mod(row, 2.0)), row);
        float mortar = max(grid_line(uv.y, 0.075, 0.012, fw), grid_line(uv.x + 0.12 * mod(row, 2.0), 0.24, 0.012, fw));
        wall *= 1.0 + t * (0.22 * (hash2(brick) - 0.5) * band(13.0, fw) + 0.12 * fbm2(uv, 0.3, fw));
        wall = mix(wall, vec3(0.62, 0.6, 0.55), 0.5 * t * mortar);
    }
#elif MATERIAL == MAT_concrete
    {
        vec2 panel = floor(uv / vec2(1.8, 1.6));
        float joints = max(grid_line(uv.x, 1.8, 0.03, fw), grid_line(uv.y, 1.6, 0.03, fw));
        wall *= (1.0 + t * (0.12 * (hash2(panel + v_param * 50.0) - 0.5) + 0.12 * fbm2(uv, 0.8, fw))) * (1.0 - 0.3 * t * joints);
    }
#else
    {  // glass curtain wall: mullion grid, panels reflecting the sky differently
        vec2 panel = floor(uv / vec2(1.5, 3.3));
        float mullion = max(grid_line(uv.x, 1.5, 0.08, fw), grid_line(uv.y, 3.3, 0.25, fw));
        float id = hash2(panel + v_param * 40.0);
        vec3 glass = wall * (0.65 + 0.7 * id * max(t, 0.3)) + 0.1 * fract(uv.y / 3.3);
        gloss = 1.0 - mullion;
        return mix(glass, vec3(0.2, 0.21, 0.22), mullion);
    }
#endif
    return windows(wall, uv, fw, gloss);
}

// Suburb ------------------------------------------------------------------------------------------
// Lawn and verge: lush and dry patches at lawn scale, clumps of darker and yellower grass at metre
// scale, tufts and blades near the camera (band-limited so the far lawn settles to its mean), and
// damp darker patches. uv: metres on the ground.
vec3 grass(vec2 uv, float fw) {
    float t = u_texture;
    float patches = fbm2(uv + v_param * 37.0, 0.05, fw);
    float clumps = fbm2(uv * vec2(1.0, 1.3) + 11.0, 0.6, fw);
    float tufts = vnoise(uv * 4.5 + 2.0) * band(4.5, fw);
    float blades = 0.6 * vnoise(uv * vec2(13.0, 17.0)) * band(15.0, fw) + 0.4 * vnoise(uv * vec2(31.0, 41.0) + 5.0) * band(36.0, fw);
    float dry = clamp(smoothstep(-0.1, 0.5, patches + 0.6 * (fract(v_param * 3.7) - 0.6)) + 0.35 * clumps, 0.0, 1.0);
    vec3 c = mix(v_color, vec3(0.47, 0.45, 0.28), 0.6 * dry * min(t, 1.0));
    c = mix(c, c * vec3(0.7, 0.85, 0.6), 0.35 * t * max(-clumps, 0.0));  // dense dark-green clumps
    float damp = smoothstep(0.2, 0.7, vnoise(uv * 0.21 + 3.0));
    return c * (1.0 + t * (0.18 * clumps + 0.22 * tufts + 0.35 * blades - 0.15 * damp));
}

// Concrete slabs: joints every 1.5 m, slab-to-slab tone, stains.
vec3 slab(vec2 uv, float fw) {
    float t = u_texture;
    float joints = max(grid_line(uv.x, 1.5, 0.02, fw), grid_line(uv.y, 1.5, 0.02, fw));
    float tone = (hash2(floor(uv / 1.5) + v_param * 13.0) - 0.5) * 0.12 * band(0.67, fw);
    float stain = smoothstep(0.5, 0.8, vnoise(uv * 0.5 + 9.0)) * 0.12 * band(0.5, fw);
    return v_color * (1.0 + t * (tone + 0.16 * fbm2(uv, 0.7, fw) - stain)) * (1.0 - 0.35 * t * joints);
}

// Roof shingles: courses along the slope (uv.y from the eave), staggered tabs of varied tone.
vec3 shingle(vec2 uv, float fw) {
    float t = u_texture;
    float row = floor(uv.y / 0.22);
    vec2 tab = vec2(floor(uv.x / 0.34 + 0.5 * mod(row, 2.0)), row);
    float courses = grid_line(uv.y, 0.22, 0.035, fw);
    float tone = (hash2(tab + v_param * 31.0) - 0.5) * 0.3 * band(3.0, fw);
    return v_color * (1.0 + t * (tone + 0.18 * fbm2(uv, 0.35, fw))) * (1.0 - 0.35 * t * courses);
}

// Window (white frame, dark glass reflecting the sky) of half size hw x hh at offset d from its centre.
vec3 house_window(vec3 c, vec2 d, vec2 half_size, float fw, float id, inout float gloss) {
    float frame = aa_band(d.x, half_size.x + 0.08, fw) * aa_band(d.y, half_size.y + 0.08, fw);
    float glass = aa_band(d.x, half_size.x, fw) * aa_band(d.y, half_size.y, fw);
    float bars = max(aa_band(d.x, 0.025, fw), aa_band(d.y, 0.025, fw)) * step(0.4, id);
    vec3 pane = mix(vec3(0.08, 0.1, 0.12), vec3(0.45, 0.52, 0.6), 0.3 + 0.5 * clamp(d.y / half_size.y * 0.5 + 0.5, 0.0, 1.0) * id);
    c = mix(c, vec3(0.9, 0.9, 0.87), frame);
    c = mix(c, mix(pane, vec3(0.9, 0.9, 0.87), bars), glass);
    gloss = max(gloss, glass * (1.0 - bars));
    return c;
}

// House walls: uv = (metres from the face centre, height), v_extra = (face half width, wall height).
// Clapboard, brick or stucco by v_param; windows on each storey; a door and sometimes a garage door
// on the street face (-y in the object frame).
vec3 house_wall(vec2 uv, float fw, inout float gloss) {
    float t = u_texture;
    vec3 c = v_color;
    float kind = fract(v_param * 5.1);
    if (kind < 0.6) {  // clapboard: a shadow line under every board
        float board = fract(uv.y / 0.18);
        c *= 1.0 - t * 0.22 * smoothstep(0.7, 1.0, board) * band(5.5, fw);
    } else if (kind < 0.82) {
        float row = floor(uv.y / 0.075);
        vec2 brick = vec2(floor(uv.x / 0.24 + 0.5 * mod(row, 2.0)), row);
        float mortar = max(grid_line(uv.y, 0.075, 0.012, fw), grid_line(uv.x + 0.12 * mod(row, 2.0), 0.24, 0.012, fw));
        c *= 1.0 + t * 0.2 * (hash2(brick) - 0.5) * band(13.0, fw);
        c = mix(c, vec3(0.66, 0.63, 0.58), 0.5 * t * mortar);
    }
    c *= 1.0 + t * 0.1 * fbm2(uv, 0.4, fw);
    c = mix(c, c * 0.6, aa_band(uv.y, 0.35, fw));  // foundation
    float storey = 2.8;
    float spacing = 2.6 + 1.4 * fract(v_param * 13.7);
    float cols = floor((2.0 * v_extra.x - 1.2) / spacing);
    float street = step(0.7, -v_normal_obj.y);
    float door_col = floor(fract(v_param * 7.9) * max(cols, 1.0));
    if (cols >= 1.0 && uv.y < v_extra.y - 0.3) {
        float fx = uv.x / spacing + 0.5 * mod(cols, 2.0);
        float col = floor(fx) + floor(cols / 2.0);
        float dx = (fract(fx) - 0.5) * spacing;
        float k = floor(uv.y / storey);
        float inside = aa_band(uv.x, cols * spacing * 0.5, fw) * step(k * storey + 2.3, v_extra.y);
        vec2 half_size = vec2(0.45 + 0.25 * fract(v_param * 3.3), 0.62);
        float id = hash2(vec2(col, k) + v_param * 50.0);
        bool is_door = street > 0.5 && k < 0.5 && abs(col - door_col) < 0.5;
        if (is_door) {
            float door = aa_band(dx, 0.5, fw) * aa_band(uv.y - 1.1, 1.05, fw) * inside;
            vec3 door_c = mix(vec3(0.25, 0.12, 0.08), vec3(0.85, 0.85, 0.82), step(0.5, fract(v_param * 9.1)));
            c = mix(c, door_c, door);
        } else {
            c = mix(c, house_window(c, vec2(dx, uv.y - k * storey - 1.5), half_size, fw, id, gloss), inside);
        }
    }
    float garage = street * step(0.6, fract(v_param * 17.3)) * step(4.5, v_extra.x);
    float gx = uv.x - sign(fract(v_param * 2.9) - 0.5) * (v_extra.x - 2.0);
    float gdoor = garage * aa_band(gx, 1.4, fw) * aa_band(uv.y - 1.1, 1.1, fw);
    vec3 gcol = vec3(0.88, 0.88, 0.85) * (1.0 - 0.15 * t * grid_line(uv.y, 0.55, 0.03, fw));
    return mix(c, gcol, gdoor);
}

// Vehicle body in the object frame (x forward, z up); v_extra = (half length, half width).
vec3 car_body(float fw, inout float gloss) {
    vec3 p = v_obj, n = v_normal_obj, c = v_color;
    float hw = v_extra.y;
    gloss = 0.8;
    if (n.x > 0.6) {
        float lamp = aa_band(abs(p.y) - (hw - 0.32), 0.17, fw) * aa_band(p.z - 0.66, 0.065, fw);
        float grille = aa_band(p.y, hw - 0.62, fw) * aa_band(p.z - 0.55, 0.09, fw);
        float plate = aa_band(p.y, 0.25, fw) * aa_band(p.z - 0.4, 0.055, fw);
        c = mix(mix(mix(c, vec3(0.05), grille), vec3(0.9, 0.9, 0.86), plate), vec3(1.0, 0.98, 0.9), lamp);
    } else if (n.x < -0.6) {
        float lamp = aa_band(abs(p.y) - (hw - 0.28), 0.16, fw) * aa_band(p.z - 0.76, 0.07, fw);
        float plate = aa_band(p.y, 0.25, fw) * aa_band(p.z - 0.55, 0.055, fw);
        c = mix(mix(c, vec3(0.9, 0.9, 0.86), plate), vec3(0.75, 0.04, 0.03), lamp);
    } else if (abs(n.y) > 0.6) {
        float seams = max(grid_line(p.x - 0.35, 100.0, 0.015, fw), grid_line(p.x + 0.75, 100.0, 0.015, fw));
        float handle = aa_band(p.z - 0.83, 0.02, fw) * max(aa_band(p.x - 0.05, 0.1, fw), aa_band(p.x + 1.05, 0.1, fw));
        c = mix(c, c * 0.35, max(seams * step(0.5, p.z), handle));
    }
    c = mix(c, vec3(0.045), aa_band(p.z - 0.3, 0.14, fw));  // bumpers and sills
    return c;
}

vec3 tyre(float fw) {
    float hub = 1.0 - smoothstep(0.5, 0.56, length(v_uv) / max(v_extra.x, 1e-3));
    float is_cap = step(0.7, abs(v_normal_obj.y));
    return mix(v_color, vec3(0.55, 0.56, 0.58), hub * is_cap);
}

// One program per material (MATERIAL is injected): llvmpipe runs every branch of a divergent
// if-chain, so specialised programs are several times faster than one program with a switch.
vec3 albedo(float fw_uv, float fw_obj, inout float gloss) {
    float t = u_texture;
#if MATERIAL == MAT_asphalt
    return asphalt(v_uv, fw_uv);
#elif MATERIAL == MAT_sidewalk
    return sidewalk(v_uv, fw_uv);
#elif MATERIAL == MAT_kerb
    return kerb(v_uv, fw_uv);
#elif MATERIAL == MAT_paint
    return v_color * (1.0 - t * 0.18 * (0.5 + 0.5 * fbm2(v_uv, 1.5, fw_uv)));
#elif MATERIAL == MAT_plaster || MATERIAL == MAT_brick || MATERIAL == MAT_concrete || MATERIAL == MAT_glass_facade
    return facade(v_uv, fw_uv, gloss);
#elif MATERIAL == MAT_roof
    return v_color * (1.0 + t * 0.3 * fbm2(v_uv, 0.5, fw_uv));
#elif MATERIAL == MAT_grass
    return grass(v_uv, fw_uv);
#elif MATERIAL == MAT_slab
    return slab(v_uv, fw_uv);
#elif MATERIAL == MAT_shingle
    return shingle(v_uv, fw_uv);
#elif MATERIAL == MAT_siding
    return house_wall(v_uv, fw_uv, gloss);
#elif MATERIAL == MAT_ground
    float n = fbm2(v_uv, 0.05, fw_uv);
    return mix(v_color, vec3(0.45, 0.4, 0.32), 0.5 + 0.5 * n) * (1.0 + t * 0.2 * fbm2(v_uv, 0.6, fw_uv));
#elif MATERIAL == MAT_foliage
    float n = 0.6 * vnoise3(v_obj * 1.7) * band(1.7, fw_obj) + 0.5 * vnoise3(v_obj * 4.3 + 9.0) * band(4.3, fw_obj)
            + 0.35 * vnoise3(v_obj * 11.0) * band(11.0, fw_obj);
    return v_color * (1.0 + t * 0.55 * n) + vec3(0.03, 0.04, 0.0) * t * max(n, 0.0);
#elif MATERIAL == MAT_bark
    return v_color * (1.0 + t * 0.3 * vnoise(v_uv * vec2(7.0, 0.9)) * band(7.0, fw_uv));
#elif MATERIAL == MAT_metal
    gloss = 0.4;
    return v_color * (1.0 + t * 0.06 * fbm2(v_uv, 1.0, fw_uv));
#elif MATERIAL == MAT_car_paint
    return car_body(fw_obj, gloss);
#elif MATERIAL == MAT_car_glass
    gloss = 1.0;
    float sky = clamp(0.5 + 0.5 * v_normal.z, 0.0, 1.0);
    return mix(vec3(0.04, 0.05, 0.06), vec3(0.35, 0.42, 0.5), 0.25 + 0.4 * sky + 0.1 * vnoise(v_obj.xz * 2.0));
#elif MATERIAL == MAT_rubber
    return tyre(fw_obj);
#elif MATERIAL == MAT_cloth
    return v_color * (1.0 + t * 0.15 * vnoise3(v_obj * 9.0) * band(9.0, fw_obj));
#else
    return v_color;  // skin, hair, lamp
#endif
}

vec3 to_linear(vec3 c) { return pow(max(c, 0.0), vec3(2.2)); }

void main() {
    float dist = length(v_cam);
    float fw_uv = footprint2(v_uv);
    float fw_obj = footprint3(v_obj);
    float gloss = 0.0;
    vec3 base = albedo(fw_uv, fw_obj, gloss);
    vec3 colour;
#if MATERIAL == MAT_shadow
    // uv runs over [-1, 1]^2 under the object; a soft rounded rectangle, fading with distance
    vec2 q = max(abs(v_uv) - 0.55, 0.0) / 0.45;
    float occlusion = (1.0 - smoothstep(0.0, 1.0, length(q))) * v_color.r * exp(-dist / u_haze_distance);
    fragColor = vec4(vec3(1.0 - occlusion), 1.0);
    return;
#elif MATERIAL == MAT_lamp
    colour = base;
#else
    {
        vec3 n = normalize(v_normal);
        vec3 view = normalize(u_cam_pos - v_world);
        if (dot(n, view) < 0.0) n = -n;  // two-sided lighting (no culling)
        float sun = max(dot(n, u_sun_dir), 0.0);
        float sky = 0.62 + 0.38 * n.z;
        float low = mix(0.75, 1.0, smoothstep(0.0, 1.2, v_world.z - u_ground_z));  // darker near the ground
        vec3 lin = to_linear(base) * (u_sun_color * sun + u_ambient * sky * low);
        vec3 h = normalize(view + u_sun_dir);
        lin += gloss * 0.12 * u_sun_color * pow(max(dot(n, h), 0.0), 30.0) * step(0.0, dot(n, u_sun_dir));  // weak: view-dependent
        colour = pow(1.0 - exp(-1.6 * lin), vec3(1.0 / 2.2));  // soft shoulder instead of clipping
    }
#endif
    float haze = 1.0 - exp(-dist / u_haze_distance);
    fragColor = vec4(mix(colour, u_haze_color, haze), 1.0);
}

#endif
