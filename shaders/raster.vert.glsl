#version 330
// Camera-space position (OpenCV axes) and a one-hot barycentric per de-indexed corner.
uniform mat4 clip_from_cam;
in vec3 in_cam;
in vec3 in_bary;
out vec3 v_bary;
out float v_z;
void main() {
    gl_Position = clip_from_cam * vec4(in_cam, 1.0);
    v_bary = in_bary;
    v_z = in_cam.z;
}
