#version 330 core
// One input image's depth as a textured triangle mesh (drivingscene/methods/depth_mesh.py): each
// vertex sits at a pixel centre back-projected to its depth (world, relative to an origin near the
// scene so that float32 keeps millimetres) and carries that pixel's colour and scene flow. At time t
// the vertex has moved u_flow_weight times its flow (the Gaussians' time rule). The colour target
// receives the interpolated colour and the camera z of the surface; its alpha stays 0 (cleared)
// where no triangle covers the pixel.

#if defined VERTEX_SHADER

uniform mat4 m_proj;         // camera -> clip
uniform mat4 m_world_to_cam; // world (origin-relative) -> target camera
uniform float u_flow_weight; // the share of its flow the vertex has moved at t

in vec3 in_position; // world at the layer's keyframe, metres, origin-relative
in vec3 in_flow;     // world displacement towards the other keyframe, metres
in vec3 in_color;    // RGB in [0, 1]

out vec3 v_color;
out float v_depth;

void main() {
    vec4 cam = m_world_to_cam * vec4(in_position + u_flow_weight * in_flow, 1.0);
    gl_Position = m_proj * cam;
    v_color = in_color;
    v_depth = cam.z;
}

#elif defined FRAGMENT_SHADER

in vec3 v_color;
in float v_depth;

out vec4 fragColor; // RGB, camera z (> 0 where covered)

void main() {
    fragColor = vec4(v_color, v_depth);
}

#endif
