//! Pinhole camera basis (DESIGN.md: right = normalize(forward × up), image row 0 at the top).

use voxlight_protocol::Camera;

/// Orthonormal camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraBasis {
    pub eye: [f32; 3],
    pub forward: [f32; 3],
    pub right: [f32; 3],
    /// The true up: right × forward (the camera's `up` made orthogonal to `forward`).
    pub up: [f32; 3],
    pub tan_half_fov: f32,
}

pub fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn length(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}

pub fn normalize(a: [f32; 3]) -> Option<[f32; 3]> {
    let len = length(a);
    (len.is_finite() && len > 1e-12).then(|| [a[0] / len, a[1] / len, a[2] / len])
}

impl CameraBasis {
    /// Fails for a degenerate camera: eye on the target, up parallel to the view direction,
    /// non-finite numbers or a field of view outside (0°, 179°).
    pub fn new(camera: &Camera) -> Result<Self, String> {
        let finite = camera
            .eye
            .iter()
            .chain(&camera.target)
            .chain(&camera.up)
            .all(|v| v.is_finite());
        if !finite {
            return Err("camera has a non-finite coordinate".into());
        }
        if !(camera.fov_deg > 0.0 && camera.fov_deg < 179.0) {
            return Err(format!(
                "fov_deg must be in (0, 179), got {}",
                camera.fov_deg
            ));
        }
        let forward =
            normalize(sub(camera.target, camera.eye)).ok_or("camera eye and target coincide")?;
        let right = normalize(cross(forward, camera.up))
            .ok_or("camera up is zero or parallel to the view direction")?;
        let up = cross(right, forward);
        Ok(Self {
            eye: camera.eye,
            forward,
            right,
            up,
            tan_half_fov: (camera.fov_deg.to_radians() * 0.5).tan(),
        })
    }

    /// Direction through continuous pixel position (x, y) of a width × height image; the
    /// CPU twin of `camera_ray_dir` in shared/scene.wgsl.
    pub fn ray_dir(&self, x: f32, y: f32, width: u32, height: u32) -> [f32; 3] {
        let aspect = width as f32 / height as f32;
        let ndc_x = (2.0 * x / width as f32 - 1.0) * aspect * self.tan_half_fov;
        let ndc_y = (1.0 - 2.0 * y / height as f32) * self.tan_half_fov;
        let d = [
            self.forward[0] + ndc_x * self.right[0] + ndc_y * self.up[0],
            self.forward[1] + ndc_x * self.right[1] + ndc_y * self.up[1],
            self.forward[2] + ndc_x * self.right[2] + ndc_y * self.up[2],
        ];
        normalize(d).unwrap_or(self.forward)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_camera_right_is_plus_x() {
        let basis = CameraBasis::new(&Camera::default()).unwrap();
        assert_eq!(basis.forward, [0.0, 1.0, 0.0]);
        assert_eq!(basis.right, [1.0, 0.0, 0.0]);
        assert_eq!(basis.up, [0.0, 0.0, 1.0]);
        // Row 0 is the top: the top-centre pixel looks up.
        let top = basis.ray_dir(32.0, 0.0, 64, 64);
        assert!(top[2] > 0.0);
        let centre = basis.ray_dir(32.0, 32.0, 64, 64);
        assert!((centre[1] - 1.0).abs() < 1e-6);
    }

    #[test]
    fn degenerate_cameras_are_rejected() {
        let mut cam = Camera::default();
        cam.target = cam.eye;
        assert!(CameraBasis::new(&cam).is_err());
        let cam = Camera {
            up: [0.0, 1.0, 0.0],
            ..Camera::default()
        };
        assert!(CameraBasis::new(&cam).is_err());
        let cam = Camera {
            fov_deg: 0.0,
            ..Camera::default()
        };
        assert!(CameraBasis::new(&cam).is_err());
        let mut cam = Camera::default();
        cam.eye[0] = f32::NAN;
        assert!(CameraBasis::new(&cam).is_err());
    }
}
