#version 330
// Triangle id + 1 (0 = background), nothing interpolated.
layout(location = 0) out int out_id;
void main() {
    out_id = gl_PrimitiveID + 1;
}
