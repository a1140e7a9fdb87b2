#version 330 core
// datagen's label pass with the surface layers: attachment 0 the segment colour (as pyrender's
// segmentation pass writes it), attachment 1 the unit world-space shading normal (the
// interpolated vertex normal, as the lit pass shades), attachment 2 the object coordinates, the
// object-frame point mapped into [0,1]^3 by its bounding box: (local - box_min) * box_scale,
// with box_scale = 1 / box size (0 for the backdrop, whose coordinates are 0).

uniform vec3 color;
uniform vec3 box_min;
uniform vec3 box_scale;

in vec3 frag_normal;
in vec3 frag_local;

layout(location = 0) out vec4 out_segment;
layout(location = 1) out vec4 out_normal;
layout(location = 2) out vec4 out_coordinates;

void main()
{
    out_segment = vec4(color, 1.0);
    out_normal = vec4(normalize(frag_normal), 1.0);
    out_coordinates = vec4(clamp((frag_local - box_min) * box_scale, 0.0, 1.0), 1.0);
}
