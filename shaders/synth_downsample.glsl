#version 330 core
// Box filter: each output pixel is the mean of a FACTOR x FACTOR block of the supersampled image,
// so colour stays consistent with intrinsics scaled by c' = (c + 0.5) * s - 0.5.

#if defined VERTEX_SHADER

in vec2 in_position;

void main() { gl_Position = vec4(in_position, 0.0, 1.0); }

#elif defined FRAGMENT_SHADER

uniform sampler2D u_image;

out vec4 fragColor;

void main() {
    ivec2 base = ivec2(gl_FragCoord.xy) * FACTOR;
    vec4 sum = vec4(0.0);
    for (int j = 0; j < FACTOR; ++j)
        for (int i = 0; i < FACTOR; ++i)
            sum += texelFetch(u_image, base + ivec2(i, j), 0);
    fragColor = sum / float(FACTOR * FACTOR);
}

#endif
