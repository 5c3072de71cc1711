#version 330
// Triangle id + 1 (0 is the clear value = background) and perspective-correct
// barycentrics with camera-space depth.
in vec3 v_bary;
in float v_z;
layout(location = 0) out int out_id;
layout(location = 1) out vec4 out_bary_depth;
void main() {
    out_id = gl_PrimitiveID + 1;
    out_bary_depth = vec4(v_bary, v_z);
}
