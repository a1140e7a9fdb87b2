#version 330 core
// datagen's lit-pass fragment shader for pyrender: textured Lambert diffuse with a Blinn-Phong
// highlight, directional lights with a 2x2 percentage-closer shadow lookup, inverse-square point
// lights and ambient light. Cheaper than pyrender's PBR shader (whose shadow filter takes 36
// texture reads per light), which matters on Mesa's software renderer. Uniform names follow
// pyrender's (datagen/render.py binds them). The numbers of lights are compile-time defines
// (NUM_DIRECTIONAL_LIGHTS, NUM_POINT_LIGHTS), so the loops unroll and every shadow sampler is
// indexed by a constant.

struct DirectionalLight {
    vec3 direction;  // the direction the light travels
    vec3 color;
    float intensity;
#ifdef DIRECTIONAL_LIGHT_SHADOWS
    sampler2D shadow_map;
    mat4 light_matrix;
#endif
};

struct PointLight {
    vec3 position;
    vec3 color;
    float intensity;
};

struct Material {
    vec4 base_color_factor;
    float roughness_factor;
#ifdef HAS_BASE_COLOR_TEX
    sampler2D base_color_texture;
#endif
};

uniform DirectionalLight directional_lights[MAX_DIRECTIONAL_LIGHTS];
uniform PointLight point_lights[MAX_POINT_LIGHTS];
uniform vec3 ambient_light;
uniform vec3 cam_pos;
uniform Material material;

in vec3 frag_position;
in vec3 frag_normal;
in vec2 uv_0;

out vec4 frag_color;

const float PI = 3.141592653589793;

#ifdef DIRECTIONAL_LIGHT_SHADOWS
// Fraction of light reaching this fragment: 4 depth comparisons half a texel around it.
float lit_fraction(sampler2D shadow_map, mat4 light_matrix, float n_dot_l)
{
    vec4 clip = light_matrix * vec4(frag_position, 1.0);
    vec3 coords = clip.xyz / clip.w * 0.5 + 0.5;
    if (coords.z > 1.0 || any(lessThan(coords.xy, vec2(0.0)))
            || any(greaterThan(coords.xy, vec2(1.0)))) {
        return 1.0;  // outside the shadow map's window: lit
    }
    // Slope-scaled depth bias: a surface tilted by theta from the light changes depth by
    // texel * tan(theta) across one shadow-map texel, and the 4 taps span about 1.5 texels.
    // The orthographic light matrix maps one scene unit to half the norm of its rows in [0, 1].
    mat3 rows = transpose(mat3(light_matrix));  // rows[i] = row i of the rotation-scale part
    float units_to_uv = 0.5 * length(rows[0]);
    float units_to_depth = 0.5 * length(rows[2]);
    float texel_units = 1.0 / (float(textureSize(shadow_map, 0).x) * units_to_uv);
    float tan_theta = sqrt(1.0 - n_dot_l * n_dot_l) / max(n_dot_l, 0.2);
    float bias = texel_units * (0.5 + 1.5 * tan_theta) * units_to_depth;
    vec2 texel = 0.5 / vec2(textureSize(shadow_map, 0));
    float depth = coords.z - bias;
    float lit = 0.0;
    lit += step(depth, texture(shadow_map, coords.xy + vec2(-texel.x, -texel.y)).r);
    lit += step(depth, texture(shadow_map, coords.xy + vec2(texel.x, -texel.y)).r);
    lit += step(depth, texture(shadow_map, coords.xy + vec2(-texel.x, texel.y)).r);
    lit += step(depth, texture(shadow_map, coords.xy + vec2(texel.x, texel.y)).r);
    return 0.25 * lit;
}
#endif

void main()
{
    vec4 base = material.base_color_factor;
#ifdef HAS_BASE_COLOR_TEX
    base *= vec4(pow(texture(material.base_color_texture, uv_0).rgb, vec3(2.2)), 1.0);
#endif
    vec3 to_camera = normalize(cam_pos - frag_position);
    vec3 n = normalize(frag_normal);
    if (dot(n, to_camera) < 0.0) {
        n = -n;  // smooth shading tilts a front face's normal away near a silhouette
    }
    float shininess = 2.0 / max(pow(material.roughness_factor, 4.0), 1e-3);
    float specular = 0.25 * (1.0 - material.roughness_factor);

    vec3 color = ambient_light * base.rgb;
    for (int i = 0; i < NUM_DIRECTIONAL_LIGHTS; i++) {
        vec3 l = -normalize(directional_lights[i].direction);
        float n_dot_l = max(dot(n, l), 0.0);
        float lit = 1.0;
#ifdef DIRECTIONAL_LIGHT_SHADOWS
        if (n_dot_l > 0.0) {
            lit = lit_fraction(directional_lights[i].shadow_map,
                               directional_lights[i].light_matrix, n_dot_l);
        }
#endif
        float highlight = specular * pow(max(dot(n, normalize(l + to_camera)), 0.0), shininess);
        color += lit * directional_lights[i].intensity * directional_lights[i].color
                 * (base.rgb / PI * n_dot_l + highlight * n_dot_l);
    }
    for (int i = 0; i < NUM_POINT_LIGHTS; i++) {
        vec3 offset = point_lights[i].position - frag_position;
        float dist2 = dot(offset, offset);
        vec3 l = offset * inversesqrt(dist2);
        float n_dot_l = max(dot(n, l), 0.0);
        float highlight = specular * pow(max(dot(n, normalize(l + to_camera)), 0.0), shininess);
        color += point_lights[i].intensity / dist2 * point_lights[i].color
                 * (base.rgb / PI * n_dot_l + highlight * n_dot_l);
    }
    frag_color = vec4(pow(clamp(color, 0.0, 1.0), vec3(1.0 / 2.2)), base.a);
}
