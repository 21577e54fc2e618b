//! The protocol's technique options: their ranges, and the technique configurations they set.
//! Each technique's own constructor still checks what only it can (memory, device limits).

use voxlight_protocol::{
    CacheInvalidation, CachedLight, IrradianceOptions, Locking, ManylightOptions,
    PhotonInvalidation, PhotonOptions, TechniqueOptions, Transmittance,
};

use crate::passes::manylight::{MAX_NODES, TransmittanceMode};
use crate::techniques::irradiance::{self, IrradianceConfig};
use crate::techniques::manylight::ManylightConfig;
use crate::techniques::photon::{self, PhotonParams};

fn in_range<T: PartialOrd + std::fmt::Display + Copy>(
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

/// Checks every option against its range (the messages name the option).
pub fn validate(options: &TechniqueOptions) -> Result<(), String> {
    let p = &options.photon;
    in_range("photon.photons_per_pass", p.photons_per_pass, 1, 1 << 20)?;
    in_range("photon.passes", p.passes, 1, 256)?;
    in_range("photon.bounces", p.bounces, 1, 64)?;
    in_range("photon.radius", p.radius, 0.0, 0.25)?;
    in_range("photon.segments", p.segments, 1, 32)?;
    let m = &options.manylight;
    in_range("manylight.virtual_lights", m.virtual_lights, 1, 16384)?;
    in_range("manylight.max_bounces", m.max_bounces, 1, 64)?;
    in_range("manylight.face_res", m.face_res, 4, 64)?;
    in_range("manylight.nodes", m.nodes, 2, MAX_NODES)?;
    in_range("manylight.vsl_radius", m.vsl_radius, 1e-4, 0.25)?;
    let i = &options.irradiance;
    in_range(
        "irradiance.bounces",
        i.bounces,
        1,
        irradiance::DEFAULT_BOUNCES,
    )?;
    in_range(
        "irradiance.max_radius_voxels",
        i.max_radius_voxels,
        0.1,
        64.0,
    )?;
    in_range("irradiance.gamma", i.gamma, 1e-3, 1.0)?;
    in_range("irradiance.epsilon", i.epsilon, 1e-3, 1.0)?;
    in_range("irradiance.view_picks", i.view_picks, 1, 16)?;
    Ok(())
}

/// `photon`'s parameters: the defaults with what `options` sets.
pub fn photon_params(options: &PhotonOptions) -> PhotonParams {
    let d = PhotonParams::default();
    PhotonParams {
        photons_per_pass: options.photons_per_pass.unwrap_or(d.photons_per_pass),
        max_passes: options.passes.unwrap_or(d.max_passes),
        bounces: options.bounces.unwrap_or(d.bounces),
        radius: options.radius.unwrap_or(d.radius),
        segments: options.segments.unwrap_or(d.segments),
        invalidation: match options.invalidation {
            None => d.invalidation,
            Some(PhotonInvalidation::AnyPhoton) => photon::Invalidation::AnyPhoton,
            Some(PhotonInvalidation::Spatial3x64) => photon::Invalidation::SpatialHistogram,
            Some(PhotonInvalidation::DirtyCells) => photon::Invalidation::DirtyCells,
        },
        ..d
    }
}

/// `manylight`'s configuration: the defaults with what `options` sets.
pub fn manylight_config(options: &ManylightOptions) -> ManylightConfig {
    let d = ManylightConfig::default();
    ManylightConfig {
        vls: options.virtual_lights.unwrap_or(d.vls),
        max_bounces: options.max_bounces.unwrap_or(d.max_bounces),
        face_res: options.face_res.unwrap_or(d.face_res),
        nodes: options.nodes.unwrap_or(d.nodes),
        mode: match options.transmittance {
            None => d.mode,
            Some(Transmittance::AvsmPoint) => TransmittanceMode::AvsmPoint,
            Some(Transmittance::AvsmTrilinear) => TransmittanceMode::AvsmTrilinear,
            Some(Transmittance::RayMarched) => TransmittanceMode::RayMarched,
        },
        vsl_radius: options.vsl_radius.unwrap_or(d.vsl_radius),
    }
}

/// `irradiance`'s configuration: the defaults with what `options` sets.
pub fn irradiance_config(options: &IrradianceOptions) -> IrradianceConfig {
    let d = IrradianceConfig::default();
    IrradianceConfig {
        cache: options.cache.unwrap_or(d.cache),
        locking: match options.locking {
            None => d.locking,
            Some(Locking::Object) => irradiance::Locking::Object,
            Some(Locking::Screen) => irradiance::Locking::Screen,
        },
        priorities: options.priorities.unwrap_or(d.priorities),
        bounces: options.bounces.unwrap_or(d.bounces),
        max_radius_voxels: options.max_radius_voxels.unwrap_or(d.max_radius_voxels),
        gamma: options.gamma.unwrap_or(d.gamma),
        epsilon: options.epsilon.unwrap_or(d.epsilon),
        invalidation: match options.invalidation {
            None => d.invalidation,
            Some(CacheInvalidation::Historygram) => irradiance::Invalidation::Historygram,
            Some(CacheInvalidation::Clear) => irradiance::Invalidation::Clear,
        },
        cached_light: match options.cached_light {
            None => d.cached_light,
            Some(CachedLight::Indirect) => irradiance::CachedLight::Indirect,
            Some(CachedLight::All) => irradiance::CachedLight::All,
        },
        view_picks: options.view_picks.unwrap_or(d.view_picks),
        ..d
    }
}

/// `technique`'s options at their defaults (empty for a technique without options), so that
/// clients can show them without a copy of the defaults.
pub fn defaults_of(technique: &str) -> TechniqueOptions {
    let mut options = TechniqueOptions::default();
    match technique {
        "photon" => {
            let p = PhotonParams::default();
            options.photon = PhotonOptions {
                photons_per_pass: Some(p.photons_per_pass),
                passes: Some(p.max_passes),
                bounces: Some(p.bounces),
                radius: Some(p.radius),
                segments: Some(p.segments),
                invalidation: Some(match p.invalidation {
                    photon::Invalidation::AnyPhoton => PhotonInvalidation::AnyPhoton,
                    photon::Invalidation::SpatialHistogram => PhotonInvalidation::Spatial3x64,
                    photon::Invalidation::DirtyCells => PhotonInvalidation::DirtyCells,
                }),
            };
        }
        "manylight" => {
            let m = ManylightConfig::default();
            options.manylight = ManylightOptions {
                virtual_lights: Some(m.vls),
                max_bounces: Some(m.max_bounces),
                face_res: Some(m.face_res),
                nodes: Some(m.nodes),
                transmittance: Some(match m.mode {
                    TransmittanceMode::AvsmPoint => Transmittance::AvsmPoint,
                    TransmittanceMode::AvsmTrilinear => Transmittance::AvsmTrilinear,
                    TransmittanceMode::RayMarched => Transmittance::RayMarched,
                }),
                vsl_radius: Some(m.vsl_radius),
            };
        }
        "irradiance" => {
            let i = IrradianceConfig::default();
            options.irradiance = IrradianceOptions {
                cache: Some(i.cache),
                locking: Some(match i.locking {
                    irradiance::Locking::Object => Locking::Object,
                    irradiance::Locking::Screen => Locking::Screen,
                }),
                priorities: Some(i.priorities),
                bounces: Some(i.bounces),
                max_radius_voxels: Some(i.max_radius_voxels),
                gamma: Some(i.gamma),
                epsilon: Some(i.epsilon),
                invalidation: Some(match i.invalidation {
                    irradiance::Invalidation::Historygram => CacheInvalidation::Historygram,
                    irradiance::Invalidation::Clear => CacheInvalidation::Clear,
                }),
                cached_light: Some(match i.cached_light {
                    irradiance::CachedLight::Indirect => CachedLight::Indirect,
                    irradiance::CachedLight::All => CachedLight::All,
                }),
                view_picks: Some(i.view_picks),
            };
        }
        _ => {}
    }
    options
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_options_are_the_defaults() {
        let none = TechniqueOptions::default();
        validate(&none).unwrap();
        assert_eq!(photon_params(&none.photon), PhotonParams::default());
        assert_eq!(
            manylight_config(&none.manylight),
            ManylightConfig::default()
        );
        assert_eq!(
            irradiance_config(&none.irradiance),
            IrradianceConfig::default()
        );
    }

    #[test]
    fn the_advertised_defaults_are_the_defaults() {
        for (name, _) in crate::techniques::ALL {
            let defaults = defaults_of(name);
            validate(&defaults).unwrap();
            assert_eq!(photon_params(&defaults.photon), PhotonParams::default());
            assert_eq!(
                manylight_config(&defaults.manylight),
                ManylightConfig::default()
            );
            assert_eq!(
                irradiance_config(&defaults.irradiance),
                IrradianceConfig::default()
            );
        }
        assert!(defaults_of("raymarch").is_empty());
        assert!(defaults_of("photon").photon.invalidation.is_some());
        assert!(defaults_of("manylight").manylight.transmittance.is_some());
        assert!(defaults_of("irradiance").irradiance.locking.is_some());
    }

    #[test]
    fn options_reach_the_configurations() {
        let options: TechniqueOptions = serde_json::from_str(
            r#"{"photon":{"photons_per_pass":4096,"invalidation":"spatial3x64","radius":0.02},
                "manylight":{"virtual_lights":1000,"transmittance":"avsm_point","face_res":48},
                "irradiance":{"locking":"screen","priorities":false,"invalidation":"clear",
                              "cached_light":"all","view_picks":4}}"#,
        )
        .unwrap();
        validate(&options).unwrap();
        let p = photon_params(&options.photon);
        assert_eq!(p.photons_per_pass, 4096);
        assert_eq!(p.invalidation, photon::Invalidation::SpatialHistogram);
        assert_eq!(p.radius, 0.02);
        assert_eq!(p.bounces, PhotonParams::default().bounces);
        let m = manylight_config(&options.manylight);
        assert_eq!((m.vls, m.face_res), (1000, 48));
        assert_eq!(m.mode, TransmittanceMode::AvsmPoint);
        assert_eq!(m.nodes, ManylightConfig::default().nodes);
        let i = irradiance_config(&options.irradiance);
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
        let message = validate(&options).unwrap_err();
        assert!(message.contains("manylight.nodes"), "{message}");
        assert!(message.contains("40"), "{message}");
        let mut options = TechniqueOptions::default();
        options.irradiance.gamma = Some(f32::NAN);
        assert!(validate(&options).unwrap_err().contains("irradiance.gamma"));
        let mut options = TechniqueOptions::default();
        options.irradiance.view_picks = Some(0);
        assert!(
            validate(&options)
                .unwrap_err()
                .contains("irradiance.view_picks")
        );
        let mut options = TechniqueOptions::default();
        options.photon.photons_per_pass = Some(0);
        assert!(
            validate(&options)
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
