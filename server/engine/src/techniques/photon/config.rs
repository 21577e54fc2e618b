//! `photon`'s side of the protocol's technique options: their ranges, the parameters they set
//! (`from_options`) and the defaults clients are shown (`as_options`).

use voxlight_protocol::{PhotonInvalidation, PhotonOptions};

use super::{Invalidation, PhotonParams};
use crate::techniques::in_range;

impl PhotonParams {
    /// Checks every option against its range (the messages name the option).
    pub fn validate_options(p: &PhotonOptions) -> Result<(), String> {
        in_range("photon.photons_per_pass", p.photons_per_pass, 1, 1 << 20)?;
        in_range("photon.passes", p.passes, 1, 256)?;
        in_range("photon.bounces", p.bounces, 1, 1024)?;
        in_range("photon.radius", p.radius, 0.0, 0.25)?;
        in_range("photon.segments", p.segments, 1, 32)?;
        // Above 0: a zero α or survival would end every pass's radius or path at once.
        in_range("photon.radius_alpha", p.radius_alpha, 0.01, 1.0)?;
        in_range("photon.roulette_survival", p.roulette_survival, 0.05, 1.0)
    }

    /// The defaults with what `options` sets.
    pub fn from_options(options: &PhotonOptions) -> Self {
        let d = PhotonParams::default();
        PhotonParams {
            photons_per_pass: options.photons_per_pass.unwrap_or(d.photons_per_pass),
            max_passes: options.passes.unwrap_or(d.max_passes),
            bounces: options.bounces.unwrap_or(d.bounces),
            radius: options.radius.unwrap_or(d.radius),
            segments: options.segments.unwrap_or(d.segments),
            radius_alpha: options.radius_alpha.unwrap_or(d.radius_alpha),
            roulette_survival: options.roulette_survival.unwrap_or(d.roulette_survival),
            invalidation: match options.invalidation {
                None => d.invalidation,
                Some(PhotonInvalidation::AnyPhoton) => Invalidation::AnyPhoton,
                Some(PhotonInvalidation::Spatial3x64) => Invalidation::SpatialHistogram,
                Some(PhotonInvalidation::DirtyCells) => Invalidation::DirtyCells,
            },
            ..d
        }
    }

    /// These parameters as options (every option set).
    pub fn as_options(&self) -> PhotonOptions {
        PhotonOptions {
            photons_per_pass: Some(self.photons_per_pass),
            passes: Some(self.max_passes),
            bounces: Some(self.bounces),
            radius: Some(self.radius),
            segments: Some(self.segments),
            radius_alpha: Some(self.radius_alpha),
            roulette_survival: Some(self.roulette_survival),
            invalidation: Some(match self.invalidation {
                Invalidation::AnyPhoton => PhotonInvalidation::AnyPhoton,
                Invalidation::SpatialHistogram => PhotonInvalidation::Spatial3x64,
                Invalidation::DirtyCells => PhotonInvalidation::DirtyCells,
            }),
        }
    }
}
