#version 330
// One grey channel of the quad's texture.
uniform sampler2D image;
in vec2 texcoord;
out vec4 color;
void main() {
    color = vec4(vec3(texture(image, texcoord).r), 1.0);
}
