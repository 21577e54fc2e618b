// Shared pieces: next-event estimation to the directional and point lights. A pass that
// includes this declares `scene: SceneUniforms`, `lights: array<GpuLight>` and
// `fn shadow_transmittance(p, dir, t_max, rng) -> f32`, its estimator of the transmittance
// from p toward a light over at most t_max.

// What one directional or point light delivers at p: its irradiance on a plane facing it,
// times the estimated transmittance, and the direction its light travels there.
struct Incidence {
    irradiance: vec3<f32>,
    travel: vec3<f32>,
}

fn light_incidence(light: GpuLight, p: vec3<f32>, rng: ptr<function, Rng>) -> Incidence {
    if (light.kind == LIGHT_DIRECTIONAL) {
        let tr = shadow_transmittance(p, -light.vector, 1e30, rng);
        return Incidence(light.color * tr, light.vector);
    }
    let offset = light.vector - p;
    let dist = length(offset);
    let to_light = offset / max(dist, 1e-6);
    let tr = shadow_transmittance(p, to_light, dist, rng);
    return Incidence(light.color / max(dist * dist, 1e-8) * tr, -to_light);
}

// Radiance from every directional and point light scattered at p toward −view_dir, per unit
// albedo (phase function included).
fn direct_light(p: vec3<f32>, view_dir: vec3<f32>, rng: ptr<function, Rng>) -> vec3<f32> {
    var s = vec3<f32>(0.0);
    for (var i = 0u; i < scene.light_count; i++) {
        let incidence = light_incidence(lights[i], p, rng);
        s += incidence.irradiance * phase_hg(dot(incidence.travel, -view_dir), scene.g);
    }
    return s;
}

// Irradiance from every directional and point light at p (no phase function): what an
// isotropic scatterer at p receives from them, integrated over directions.
fn direct_irradiance(p: vec3<f32>, rng: ptr<function, Rng>) -> vec3<f32> {
    var e = vec3<f32>(0.0);
    for (var i = 0u; i < scene.light_count; i++) {
        e += light_incidence(lights[i], p, rng).irradiance;
    }
    return e;
}
