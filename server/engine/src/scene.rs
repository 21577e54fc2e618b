//! What a session renders (the physical model of DESIGN.md) and how it changes.

use voxlight_protocol::{
    Camera, Light, MAX_LIGHTS, MAX_VIEWPORT_EDGE, RenderParams, TechniqueOptions, TransferFunction,
    Viewport, default_lights,
};

/// Everything a technique needs besides the volume.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub camera: Camera,
    pub tf: TransferFunction,
    pub lights: Vec<Light>,
    pub params: RenderParams,
    pub viewport: Viewport,
    /// Seed of the counter-based random numbers.
    pub seed: u32,
    /// Progressive iterations after which the picture is converged.
    pub target_iterations: u32,
    /// Settings of the techniques (read when a renderer is built).
    pub technique_options: TechniqueOptions,
}

impl Default for Scene {
    fn default() -> Self {
        Self {
            camera: Camera::default(),
            tf: TransferFunction::default(),
            lights: default_lights(),
            params: RenderParams::default(),
            viewport: Viewport::default(),
            seed: 0,
            target_iterations: 256,
            technique_options: TechniqueOptions::default(),
        }
    }
}

/// One edit, applied to a technique after the `Scene` was updated. `Tf` carries the previous
/// transfer function and the query historygram of the edit (bins whose optics changed).
#[derive(Debug, Clone, PartialEq)]
pub enum Change {
    Camera,
    Tf {
        old: TransferFunction,
        query_historygram: u64,
    },
    Lights,
    Params,
    Viewport,
    Iterations,
}

impl Change {
    /// A TF change with its query historygram.
    pub fn tf(old: &TransferFunction, new: &TransferFunction) -> Self {
        Change::Tf {
            old: old.clone(),
            query_historygram: crate::tf::query_historygram(old, new),
        }
    }
}

fn finite3(v: &[f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn non_negative3(v: &[f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite() && *x >= 0.0)
}

pub fn validate_lights(lights: &[Light]) -> Result<(), String> {
    if lights.len() > MAX_LIGHTS {
        return Err(format!("at most {MAX_LIGHTS} lights, got {}", lights.len()));
    }
    for (i, light) in lights.iter().enumerate() {
        let ok = match light {
            Light::Directional {
                direction,
                irradiance,
            } => {
                finite3(direction)
                    && crate::camera::length(*direction) > 1e-6
                    && non_negative3(irradiance)
            }
            Light::Point {
                position,
                intensity,
            } => finite3(position) && non_negative3(intensity),
            Light::Environment { radiance } => non_negative3(radiance),
        };
        if !ok {
            return Err(format!(
                "light {i}: coordinates must be finite, colours non-negative and directions non-zero"
            ));
        }
    }
    Ok(())
}

pub fn validate_params(params: &RenderParams) -> Result<(), String> {
    if !(params.density_scale.is_finite() && (0.0..=1e5).contains(&params.density_scale)) {
        return Err(format!(
            "density_scale must be in [0, 100000], got {}",
            params.density_scale
        ));
    }
    if !(params.g.is_finite() && params.g > -0.99 && params.g < 0.99) {
        return Err(format!("g must be in (-0.99, 0.99), got {}", params.g));
    }
    if !(params.exposure.is_finite() && params.exposure > 0.0 && params.exposure <= 1e4) {
        return Err(format!(
            "exposure must be in (0, 10000], got {}",
            params.exposure
        ));
    }
    Ok(())
}

pub fn validate_viewport(viewport: &Viewport) -> Result<(), String> {
    let ok = |e: u32| (1..=MAX_VIEWPORT_EDGE).contains(&e);
    if !ok(viewport.width) || !ok(viewport.height) {
        return Err(format!(
            "viewport must be between 1×1 and {MAX_VIEWPORT_EDGE}×{MAX_VIEWPORT_EDGE}, got {}×{}",
            viewport.width, viewport.height
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_scene_is_valid() {
        Scene::default().validate().unwrap();
    }

    #[test]
    fn bad_parts_are_named() {
        let scene = Scene {
            viewport: Viewport {
                width: 0,
                height: 10,
            },
            ..Scene::default()
        };
        assert!(scene.validate().unwrap_err().contains("viewport"));
        let mut scene = Scene::default();
        scene.params.g = 1.0;
        assert!(scene.validate().unwrap_err().contains("g must"));
        let scene = Scene {
            lights: vec![Light::Directional {
                direction: [0.0; 3],
                irradiance: [1.0; 3],
            }],
            ..Scene::default()
        };
        assert!(scene.validate().unwrap_err().contains("light 0"));
    }
}
