//! The rendering techniques. Each owns only per-session buffers; pipelines live in `Engine`.
//!
//! - One module per technique (`photon/`, `manylight/`, `irradiance/`; `progressive.rs` is
//!   `raymarch` and `pathtrace`); each technique's `config.rs` owns its side of the protocol's
//!   `TechniqueOptions` (`validate_options`, `from_options`, `as_options`).
//! - `validate_options` and `default_options` here cover every technique.

use voxlight_protocol::{TechniqueKind, TechniqueOptions};

use self::irradiance::IrradianceConfig;
use self::manylight::ManylightConfig;
use self::photon::PhotonParams;

pub mod irradiance;
pub mod manylight;
pub mod photon;
pub mod progressive;

/// One-line description of a technique, as clients list it.
pub fn description(kind: TechniqueKind) -> &'static str {
    match kind {
        TechniqueKind::Raymarch => {
            "Single scattering with shadow rays to every light and the environment (fast preview; no multiple scattering)"
        }
        TechniqueKind::Pathtrace => {
            "Unbiased Monte-Carlo path tracing with delta tracking and next-event estimation (the reference; multiple scattering)"
        }
        TechniqueKind::Manylight => {
            "Single scattering plus multiple scattering from virtual spherical lights with transmittance cached in adaptive volumetric shadow maps (Weber et al. 2013)"
        }
        TechniqueKind::Irradiance => {
            "Monte-Carlo volume rendering whose first scattering event reads a parallel irradiance cache built while rendering (Khlebnikov et al. 2014), with multiple scattering; the lights' direct light is traced with shadow rays and the cache holds the indirect light (isotropic phase function; zones interpolate it over a few voxels: slightly biased there); TF edits keep the entries they cannot change"
        }
        TechniqueKind::Photon => {
            "Volumetric photon mapping with historygrams: progressive photon passes, view-ray segments; TF edits retrace only affected photons and segments (multiple scattering, kernel-density bias)"
        }
    }
}

/// Checks that an option, when given, is in `[low, high]` (the message names it).
pub(crate) fn in_range<T: PartialOrd + std::fmt::Display + Copy>(
    name: &str,
    value: Option<T>,
    low: T,
    high: T,
) -> Result<(), String> {
    match value {
        Some(v) if !(low <= v && v <= high) => {
            Err(format!("{name} must be in [{low}, {high}], got {v}"))
        }
        _ => Ok(()),
    }
}

/// Checks every technique's options against their ranges. Each technique's constructor still
/// checks what only it can (memory, device limits).
pub fn validate_options(options: &TechniqueOptions) -> Result<(), String> {
    PhotonParams::validate_options(&options.photon)?;
    ManylightConfig::validate_options(&options.manylight)?;
    IrradianceConfig::validate_options(&options.irradiance)
}

/// `technique`'s options at their defaults (empty for a technique without options), so that
/// clients can show them without a copy of the defaults.
pub fn default_options(technique: TechniqueKind) -> TechniqueOptions {
    let mut options = TechniqueOptions::default();
    match technique {
        TechniqueKind::Photon => options.photon = PhotonParams::default().as_options(),
        TechniqueKind::Manylight => options.manylight = ManylightConfig::default().as_options(),
        TechniqueKind::Irradiance => options.irradiance = IrradianceConfig::default().as_options(),
        TechniqueKind::Raymarch | TechniqueKind::Pathtrace => {}
    }
    options
}

#[cfg(test)]
mod tests {
    use voxlight_protocol::{Locking, TechniqueOptions, Transmittance};

    use super::*;
    use crate::techniques::irradiance::{self, IrradianceConfig};
    use crate::techniques::manylight::ManylightConfig;
    use crate::techniques::manylight::gpu::TransmittanceMode;
    use crate::techniques::photon::{self, PhotonParams};

    #[test]
    fn no_options_are_the_defaults() {
        let none = TechniqueOptions::default();
        validate_options(&none).unwrap();
        assert_eq!(
            PhotonParams::from_options(&none.photon),
            PhotonParams::default()
        );
        assert_eq!(
            ManylightConfig::from_options(&none.manylight),
            ManylightConfig::default()
        );
        assert_eq!(
            IrradianceConfig::from_options(&none.irradiance),
            IrradianceConfig::default()
        );
    }

    #[test]
    fn the_advertised_defaults_are_the_defaults() {
        for kind in TechniqueKind::ALL {
            let defaults = default_options(kind);
            validate_options(&defaults).unwrap();
            assert_eq!(
                PhotonParams::from_options(&defaults.photon),
                PhotonParams::default()
            );
            assert_eq!(
                ManylightConfig::from_options(&defaults.manylight),
                ManylightConfig::default()
            );
            assert_eq!(
                IrradianceConfig::from_options(&defaults.irradiance),
                IrradianceConfig::default()
            );
        }
        assert!(default_options(TechniqueKind::Raymarch).is_empty());
        assert!(
            default_options(TechniqueKind::Photon)
                .photon
                .invalidation
                .is_some()
        );
        assert!(
            default_options(TechniqueKind::Manylight)
                .manylight
                .transmittance
                .is_some()
        );
        assert!(
            default_options(TechniqueKind::Irradiance)
                .irradiance
                .locking
                .is_some()
        );
    }

    #[test]
    fn options_reach_the_configurations() {
        let options: TechniqueOptions = serde_json::from_str(
            r#"{"photon":{"photons_per_pass":4096,"invalidation":"spatial3x64","radius":0.02,
                           "radius_alpha":1.0,"roulette_survival":1.0},
                "manylight":{"virtual_lights":1000,"transmittance":"avsm_point","face_res":48},
                "irradiance":{"locking":"screen","priorities":false,"invalidation":"clear",
                              "cached_light":"all","view_picks":4}}"#,
        )
        .unwrap();
        validate_options(&options).unwrap();
        let p = PhotonParams::from_options(&options.photon);
        assert_eq!(p.photons_per_pass, 4096);
        assert_eq!(p.invalidation, photon::Invalidation::SpatialHistogram);
        assert_eq!(p.radius, 0.02);
        assert_eq!(p.bounces, PhotonParams::default().bounces);
        // The paper's configuration: one radius, no roulette.
        assert_eq!((p.radius_alpha, p.roulette_survival), (1.0, 1.0));
        let m = ManylightConfig::from_options(&options.manylight);
        assert_eq!((m.vls, m.face_res), (1000, 48));
        assert_eq!(m.mode, TransmittanceMode::AvsmPoint);
        assert_eq!(m.nodes, ManylightConfig::default().nodes);
        let i = IrradianceConfig::from_options(&options.irradiance);
        assert_eq!(i.locking, irradiance::Locking::Screen);
        assert!(!i.priorities);
        assert_eq!(i.invalidation, irradiance::Invalidation::Clear);
        assert_eq!(i.cached_light, irradiance::CachedLight::All);
        assert_eq!(i.view_picks, 4);
        assert!(i.cache);
    }

    #[test]
    fn out_of_range_options_are_named() {
        let mut options = TechniqueOptions::default();
        options.manylight.nodes = Some(40);
        let message = validate_options(&options).unwrap_err();
        assert!(message.contains("manylight.nodes"), "{message}");
        assert!(message.contains("40"), "{message}");
        let mut options = TechniqueOptions::default();
        options.irradiance.gamma = Some(f32::NAN);
        assert!(
            validate_options(&options)
                .unwrap_err()
                .contains("irradiance.gamma")
        );
        let mut options = TechniqueOptions::default();
        options.irradiance.view_picks = Some(0);
        assert!(
            validate_options(&options)
                .unwrap_err()
                .contains("irradiance.view_picks")
        );
        let mut options = TechniqueOptions::default();
        options.photon.roulette_survival = Some(0.0);
        assert!(
            validate_options(&options)
                .unwrap_err()
                .contains("photon.roulette_survival")
        );
        let mut options = TechniqueOptions::default();
        options.photon.photons_per_pass = Some(0);
        assert!(
            validate_options(&options)
                .unwrap_err()
                .contains("photon.photons_per_pass")
        );
    }

    #[test]
    fn an_edit_changes_only_what_it_names() {
        let mut base = TechniqueOptions::default();
        base.manylight.virtual_lights = Some(64);
        base.irradiance.locking = Some(Locking::Screen);
        let mut edit = TechniqueOptions::default();
        edit.manylight.transmittance = Some(Transmittance::RayMarched);
        let merged = base.overlaid(&edit);
        assert_eq!(merged.manylight.virtual_lights, Some(64));
        assert_eq!(
            merged.manylight.transmittance,
            Some(Transmittance::RayMarched)
        );
        assert_eq!(merged.irradiance.locking, Some(Locking::Screen));
        let unknown = serde_json::from_str::<TechniqueOptions>(r#"{"manylight":{"vls":3}}"#);
        assert!(unknown.is_err(), "unknown option names are refused");
    }
}
