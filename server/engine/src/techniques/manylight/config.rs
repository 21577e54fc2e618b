//! `manylight`'s side of the protocol's technique options: their ranges, the configuration
//! they set (`from_options`) and the defaults clients are shown (`as_options`).

use voxlight_protocol::{ManylightOptions, Transmittance};

use super::ManylightConfig;
use crate::techniques::in_range;
use crate::techniques::manylight::gpu::{MAX_NODES, TransmittanceMode};

impl ManylightConfig {
    /// Checks every option against its range (the messages name the option).
    pub fn validate_options(m: &ManylightOptions) -> Result<(), String> {
        in_range("manylight.virtual_lights", m.virtual_lights, 1, 16384)?;
        in_range("manylight.max_bounces", m.max_bounces, 1, 64)?;
        in_range("manylight.face_res", m.face_res, 4, 64)?;
        in_range("manylight.nodes", m.nodes, 2, MAX_NODES)?;
        in_range("manylight.vsl_radius", m.vsl_radius, 1e-4, 0.25)?;
        in_range(
            "manylight.iterations_per_set",
            m.iterations_per_set,
            0,
            1024,
        )
    }

    /// The defaults with what `options` sets.
    pub fn from_options(options: &ManylightOptions) -> Self {
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
            iterations_per_set: options.iterations_per_set.unwrap_or(d.iterations_per_set),
        }
    }

    /// This configuration as options (every option set).
    pub fn as_options(&self) -> ManylightOptions {
        ManylightOptions {
            virtual_lights: Some(self.vls),
            max_bounces: Some(self.max_bounces),
            face_res: Some(self.face_res),
            nodes: Some(self.nodes),
            transmittance: Some(match self.mode {
                TransmittanceMode::AvsmPoint => Transmittance::AvsmPoint,
                TransmittanceMode::AvsmTrilinear => Transmittance::AvsmTrilinear,
                TransmittanceMode::RayMarched => Transmittance::RayMarched,
            }),
            vsl_radius: Some(self.vsl_radius),
            iterations_per_set: Some(self.iterations_per_set),
        }
    }
}
