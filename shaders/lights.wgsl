// Shared pieces: next-event estimation to the directional and point lights. A pass that
// includes this declares `scene: SceneUniforms`, `lights: array<GpuLight>` and
// `fn shadow_transmittance(p, dir, t_max, rng) -> f32`, its estimator of the transmittance
// from p toward a light over at most t_max.

// Radiance from every directional and point light scattered at p toward −view_dir, per unit
// albedo (phase function included).
fn direct_light(p: vec3<f32>, view_dir: vec3<f32>, rng: ptr<function, Rng>) -> vec3<f32> {
    var s = vec3<f32>(0.0);
    for (var i = 0u; i < scene.light_count; i++) {
        let light = lights[i];
        if (light.kind == LIGHT_DIRECTIONAL) {
            let tr = shadow_transmittance(p, -light.vector, 1e30, rng);
            s += light.color * tr * phase_hg(dot(light.vector, -view_dir), scene.g);
        } else {
            let offset = light.vector - p;
            let dist = length(offset);
            let to_light = offset / max(dist, 1e-6);
            let tr = shadow_transmittance(p, to_light, dist, rng);
            let irradiance = light.color / max(dist * dist, 1e-8);
            s += irradiance * tr * phase_hg(dot(-to_light, -view_dir), scene.g);
        }
    }
    return s;
}
