#version 330 core
// Ground-truth pass of the synthetic town, rendered at output resolution without multisampling so
// every value is exact at the pixel centre. Each vertex carries its position in the camera at the
// current keyframe, its position in the same camera at the other keyframe (the object and the ego
// both moved), and the world-frame displacement; all are affine in the object-frame vertex, so the
// perspective-correct interpolation of each triangle is exact.

#if defined VERTEX_SHADER

uniform mat4 m_proj;           // camera -> clip at this keyframe
uniform mat4 m_model_to_cam;   // object -> camera, now
uniform mat4 m_model_to_other; // object -> same camera at the other keyframe
uniform mat4 m_delta_world;    // object -> world at the other keyframe minus now (zero for static objects)

in vec3 in_position;

out vec3 v_now;
out vec3 v_other;
out vec3 v_scene_flow;

void main() {
    vec4 p = vec4(in_position, 1.0);
    vec4 cam = m_model_to_cam * p;
    gl_Position = m_proj * cam;
    v_now = cam.xyz;
    v_other = (m_model_to_other * p).xyz;
    v_scene_flow = (m_delta_world * p).xyz;
}

#elif defined FRAGMENT_SHADER

uniform float u_dynamic;   // 1 for independently moving objects
uniform float u_object_id; // 1-based, 0 for the static town

in vec3 v_now;
in vec3 v_other;
in vec3 v_scene_flow;

layout(location = 0) out vec4 out_now;    // camera-frame point now, dynamic flag
layout(location = 1) out vec4 out_other;  // camera-frame point at the other keyframe, coverage (1)
layout(location = 2) out vec4 out_flow;   // world displacement, object id

void main() {
    out_now = vec4(v_now, u_dynamic);
    out_other = vec4(v_other, 1.0);
    out_flow = vec4(v_scene_flow, u_object_id);
}

#endif
