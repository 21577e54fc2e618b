//! The rendering techniques. Each owns only per-session buffers; pipelines live in `Engine`.

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
];
