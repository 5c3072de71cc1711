#version 330
// Untextured geometry under a key light at an angle (Lambert, two-sided: the normal is
// turned toward the camera) plus an ambient term, so that folds show as light and shade.
// Cloth (v_matte = 0) and body (v_matte = 1) each in one colour. Camera coordinates.
uniform vec3 light_dir;      // unit vector from the surface toward the light
uniform float ambient;
uniform float diffuse;
uniform vec3 cloth_color;
uniform vec3 matte_color;
in vec3 v_cam;
in vec3 v_normal;
flat in float v_matte;
out vec4 out_color;
void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, -v_cam) < 0.0) n = -n;
    float lambert = max(dot(n, light_dir), 0.0);
    vec3 albedo = v_matte > 0.5 ? matte_color : cloth_color;
    out_color = vec4(albedo * (ambient + diffuse * lambert), 1.0);
}
