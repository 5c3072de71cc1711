#version 330
// Camera-space position (OpenCV axes) only: for a triangle-id raster without attributes.
uniform mat4 clip_from_cam;
in vec3 in_cam;
void main() {
    gl_Position = clip_from_cam * vec4(in_cam, 1.0);
}
