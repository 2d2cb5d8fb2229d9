#version 330 core
// Draws the rendered view texture into a viewport rectangle. Depth mode: the target holds
// (sum w z, ., ., sum w); the expected depth sum(w z) / sum(w) is colour-mapped linearly in inverse
// depth between u_depth_range (near, far metres) with the turbo map of drivingscene.viz.depth_to_rgb.

#if defined VERTEX_SHADER

out vec2 v_uv;

void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    v_uv = p;
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

uniform sampler2D u_image;
uniform sampler2D u_lut;       // 256 x 1
uniform int u_mode;            // 0 colour, 1 expected depth
uniform vec2 u_depth_range;    // metres: near (red), far (blue)
in vec2 v_uv;
out vec4 fragColor;

void main() {
    vec4 value = texture(u_image, v_uv);
    if (u_mode == 1) {
        if (value.a < 1e-6) { fragColor = vec4(0.0, 0.0, 0.0, 1.0); return; }
        float depth = value.r / value.a;
        float inv_near = 1.0 / u_depth_range.x, inv_far = 1.0 / u_depth_range.y;
        float x = clamp((1.0 / depth - inv_far) / (inv_near - inv_far), 0.0, 1.0);
        fragColor = vec4(texture(u_lut, vec2(x * (255.0 / 256.0) + 0.5 / 256.0, 0.5)).rgb, 1.0);
        return;
    }
    fragColor = vec4(clamp(value.rgb, 0.0, 1.0), 1.0);
}

#endif
