//! Whole-scene checks: every part of a [`Scene`], its technique options included. Apart from
//! `scene.rs` because the options are checked by the techniques, which build on the scene
//! (`scene` → `techniques` → `scene` would be a circle).

use crate::camera::CameraBasis;
use crate::scene::{Scene, validate_lights, validate_params, validate_viewport};

impl Scene {
    /// Checks every part of the scene.
    pub fn validate(&self) -> Result<(), String> {
        CameraBasis::new(&self.camera)?;
        crate::tf::validate(&self.tf)?;
        validate_lights(&self.lights)?;
        validate_params(&self.params)?;
        validate_viewport(&self.viewport)?;
        crate::techniques::validate_options(&self.technique_options)
    }
}
