#version 330
// A textured planar quad (e.g. a printed calibration board) seen by an OpenCV camera.
uniform mat4 clip_from_cam;
uniform mat4 cam_from_local;
in vec3 in_local;
in vec2 in_texcoord;
out vec2 texcoord;
void main() {
    texcoord = in_texcoord;
    gl_Position = clip_from_cam * (cam_from_local * vec4(in_local, 1.0));
}
