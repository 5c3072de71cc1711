#version 330
uniform mat4 clip_from_cam;
in vec3 in_cam;
in vec3 in_normal;
in float in_matte;
out vec3 v_cam;
out vec3 v_normal;
flat out float v_matte;
void main() {
    gl_Position = clip_from_cam * vec4(in_cam, 1.0);
    v_cam = in_cam;
    v_normal = in_normal;
    v_matte = in_matte;
}
