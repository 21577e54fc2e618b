//! voxlight's benchmarks (`voxlight bench …`): what the engine, the server and the loaders cost,
//! measured the way `docs/benchmarks.md` reports it. Speed is measured here, never in tests.
//!
//! - `engine`: `raymarch`, `preview` and `tf-edit` (historygram updates vs full recomputes,
//!   and the photon census) on the engine directly.
//! - `irradiance`: `convergence` and its `--ceiling`, and `tf-edit --technique irradiance`.
//! - `manylight`: AVSM vs ray-marched transmittance, and the many-light rebuild after edits.
//! - `interactive`: a scripted drag against a real server, input to frame.
//! - `vtk`: the full-resolution preview beside VTK's FixedPoint ray caster, in one run.
//! - `load`: time and peak host memory of loading each dataset.

pub mod cli;
pub mod engine;
pub mod interactive;
pub mod irradiance;
pub mod load;
pub mod manylight;
pub mod vtk;
