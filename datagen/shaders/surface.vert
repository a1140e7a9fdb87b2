#version 330 core
// datagen's label pass with the surface layers, for pyrender: world-space shading normal and
// object-frame position per fragment. The clip position is computed exactly as pyrender's
// segmentation program computes it (same expression), so the depth and the pixels are those of
// the label pass without the surface layers.

layout(location = 0) in vec3 position;
#ifdef NORMAL_LOC
layout(location = NORMAL_LOC) in vec3 normal;
#endif
layout(location = INST_M_LOC) in mat4 inst_m;

uniform mat4 M;
uniform mat4 V;
uniform mat4 P;

out vec3 frag_normal;
out vec3 frag_local;

void main()
{
    mat4 light_matrix = P * V;
    gl_Position = light_matrix * M * inst_m * vec4(position, 1.0);
    // Object poses are rigid (scale is baked into the vertices): the normal matrix is the
    // rotation of the model matrix, and the vertex position is the point in the object's frame.
#ifdef NORMAL_LOC
    frag_normal = mat3(M * inst_m) * normal;
#else
    frag_normal = vec3(0.0, 0.0, 1.0);
#endif
    frag_local = position;
}
