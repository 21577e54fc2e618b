//! `irradiance`'s side of the protocol's technique options: their ranges, the configuration
//! they set (`from_options`) and the defaults clients are shown (`as_options`).

use voxlight_protocol::{CacheInvalidation, CachedLight, IrradianceOptions, Locking};

use super::{DEFAULT_BOUNCES, IrradianceConfig};
use crate::techniques::in_range;

impl IrradianceConfig {
    /// Checks every option against its range (the messages name the option).
    pub fn validate_options(i: &IrradianceOptions) -> Result<(), String> {
        in_range("irradiance.bounces", i.bounces, 1, DEFAULT_BOUNCES)?;
        in_range(
            "irradiance.max_radius_voxels",
            i.max_radius_voxels,
            0.1,
            64.0,
        )?;
        in_range("irradiance.gamma", i.gamma, 1e-3, 1.0)?;
        in_range("irradiance.epsilon", i.epsilon, 1e-3, 1.0)?;
        in_range("irradiance.view_picks", i.view_picks, 1, 16)
    }

    /// The defaults with what `options` sets.
    pub fn from_options(options: &IrradianceOptions) -> Self {
        let d = IrradianceConfig::default();
        IrradianceConfig {
            cache: options.cache.unwrap_or(d.cache),
            locking: match options.locking {
                None => d.locking,
                Some(Locking::Object) => super::Locking::Object,
                Some(Locking::Screen) => super::Locking::Screen,
            },
            priorities: options.priorities.unwrap_or(d.priorities),
            bounces: options.bounces.unwrap_or(d.bounces),
            max_radius_voxels: options.max_radius_voxels.unwrap_or(d.max_radius_voxels),
            gamma: options.gamma.unwrap_or(d.gamma),
            epsilon: options.epsilon.unwrap_or(d.epsilon),
            invalidation: match options.invalidation {
                None => d.invalidation,
                Some(CacheInvalidation::Historygram) => super::Invalidation::Historygram,
                Some(CacheInvalidation::Clear) => super::Invalidation::Clear,
            },
            cached_light: match options.cached_light {
                None => d.cached_light,
                Some(CachedLight::Indirect) => super::CachedLight::Indirect,
                Some(CachedLight::All) => super::CachedLight::All,
            },
            view_picks: options.view_picks.unwrap_or(d.view_picks),
            ..d
        }
    }

    /// This configuration as options (every option set).
    pub fn as_options(&self) -> IrradianceOptions {
        IrradianceOptions {
            cache: Some(self.cache),
            locking: Some(match self.locking {
                super::Locking::Object => Locking::Object,
                super::Locking::Screen => Locking::Screen,
            }),
            priorities: Some(self.priorities),
            bounces: Some(self.bounces),
            max_radius_voxels: Some(self.max_radius_voxels),
            gamma: Some(self.gamma),
            epsilon: Some(self.epsilon),
            invalidation: Some(match self.invalidation {
                super::Invalidation::Historygram => CacheInvalidation::Historygram,
                super::Invalidation::Clear => CacheInvalidation::Clear,
            }),
            cached_light: Some(match self.cached_light {
                super::CachedLight::Indirect => CachedLight::Indirect,
                super::CachedLight::All => CachedLight::All,
            }),
            view_picks: Some(self.view_picks),
        }
    }
}
