//! The rendering techniques. Each owns only per-session buffers; pipelines live in `Engine`.

pub mod manylight;
pub mod photon;
pub mod progressive;

/// Name and one-line description of every technique, in the order clients list them.
pub const ALL: &[(&str, &str)] = &[
    (
        "raymarch",
        "Single scattering with shadow rays to every light and the environment (fast preview; no multiple scattering)",
    ),
    (
        "pathtrace",
        "Unbiased Monte-Carlo path tracing with delta tracking and next-event estimation (the reference; multiple scattering)",
    ),
    (
        "manylight",
        "Single scattering plus multiple scattering from virtual spherical lights with transmittance cached in adaptive volumetric shadow maps (Weber et al. 2013)",
    ),
    (
        "photon",
        "Volumetric photon mapping with historygrams: progressive photon passes, view-ray segments; TF edits retrace only affected photons and segments (multiple scattering, kernel-density bias)",
    ),
];
