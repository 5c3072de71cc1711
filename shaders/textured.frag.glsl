#version 330
// Fabric texture under a head light (both sides lit) with a little ambient term.
uniform sampler2D fabric;
in vec3 v_cam;
in vec3 v_normal;
in vec2 v_texcoord;
out vec4 out_color;
void main() {
    vec3 n = normalize(v_normal);
    vec3 view = normalize(-v_cam);
    float lambert = abs(dot(n, view));
    vec3 albedo = texture(fabric, v_texcoord).rgb;
    out_color = vec4(albedo * (0.25 + 0.75 * lambert), 1.0);
}
