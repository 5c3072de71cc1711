#version 330
// Fabric texture under a head light (both sides lit) with a little ambient term; the body
// (v_matte = 1) in one matte colour under the same light.
uniform sampler2D fabric;
uniform vec3 matte_color;
in vec3 v_cam;
in vec3 v_normal;
in vec2 v_texcoord;
flat in float v_matte;
out vec4 out_color;
void main() {
    vec3 n = normalize(v_normal);
    vec3 view = normalize(-v_cam);
    float lambert = abs(dot(n, view));
    vec3 albedo = v_matte > 0.5 ? matte_color : texture(fabric, v_texcoord).rgb;
    out_color = vec4(albedo * (0.25 + 0.75 * lambert), 1.0);
}
