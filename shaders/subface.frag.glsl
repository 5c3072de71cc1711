#version 330
// Triangle id + 1 (0 = background). With levels > 0 the id is that of the midpoint-
// subdivided child face containing the pixel centre, found from the perspective-correct
// barycentrics in the drawn (base) face: children of face f are k * m + f for corner
// children k = 0, 1, 2 (barycentric of corner k above 1/2) and the centre child k = 3
// (`mvtex.data.mesh.subdivide`'s order); the barycentrics are then mapped into the child.
// Primitives from num_faces on are an occluder's (the body): face j gets body_offset + j.
// Location 1 (where the framebuffer has it) receives the child barycentrics and the depth.
uniform int num_faces;
uniform int levels;
uniform int body_offset;
in vec3 v_bary;
in float v_z;
layout(location = 0) out int out_id;
layout(location = 1) out vec4 out_bary_depth;
void main() {
    vec3 b = v_bary;
    int f = gl_PrimitiveID;
    if (f >= num_faces) {
        out_id = body_offset + (f - num_faces) + 1;
        out_bary_depth = vec4(0.0);
        return;
    }
    int m = num_faces;
    for (int level = 0; level < levels; ++level) {
        int k;
        if (b.x > 0.5) { k = 0; b = vec3(2.0 * b.x - 1.0, 2.0 * b.y, 2.0 * b.z); }
        else if (b.y > 0.5) { k = 1; b = vec3(2.0 * b.x, 2.0 * b.y - 1.0, 2.0 * b.z); }
        else if (b.z > 0.5) { k = 2; b = vec3(2.0 * b.x, 2.0 * b.y, 2.0 * b.z - 1.0); }
        else { k = 3; b = vec3(1.0 - 2.0 * b.z, 1.0 - 2.0 * b.x, 1.0 - 2.0 * b.y); }
        f = k * m + f;
        m = 4 * m;
    }
    out_id = f + 1;
    out_bary_depth = vec4(b, v_z);
}
