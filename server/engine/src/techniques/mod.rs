//! The rendering techniques. Each owns only per-session buffers; pipelines live in `Engine`.

pub mod irradiance;
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
        "irradiance",
        "Monte-Carlo volume rendering whose first scattering event reads a parallel irradiance cache built while rendering (Khlebnikov et al. 2014), with multiple scattering; the lights' direct light is traced with shadow rays and the cache holds the indirect light (isotropic phase function; zones interpolate it over a few voxels: slightly biased there); TF edits keep the entries they cannot change",
    ),
    (
        "photon",
        "Volumetric photon mapping with historygrams: progressive photon passes, view-ray segments; TF edits retrace only affected photons and segments (multiple scattering, kernel-density bias)",
    ),
];
