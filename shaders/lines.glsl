#version 330 core
// Overlay lines (rig frusta, ego path, ground grid) in world coordinates, projected with the same
// pinhole camera as the splats: clip = P_K (world_to_cam p), P_K built from the intrinsics K.

#if defined VERTEX_SHADER

in vec3 in_position;  // origin-relative world
in vec4 in_color;
uniform mat4 m_proj;  // camera (OpenCV) to clip
uniform mat4 m_view;  // world to camera
out vec4 v_color;

void main() {
    v_color = in_color;
    gl_Position = m_proj * m_view * vec4(in_position, 1.0);
}

#elif defined FRAGMENT_SHADER

in vec4 v_color;
out vec4 fragColor;

void main() { fragColor = v_color; }

#endif
