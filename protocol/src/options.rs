//! Settings of the individual techniques, beyond the scene every technique shares. Every field
//! is optional: absent means the technique's default (`docs/protocol.md` lists them and their
//! ranges). A session keeps one `TechniqueOptions` for all techniques, so switching technique
//! and back keeps what was set.

use serde::{Deserialize, Serialize};

/// Options of every technique, one group per technique; a technique reads only its own.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TechniqueOptions {
    #[serde(skip_serializing_if = "PhotonOptions::is_empty")]
    pub photon: PhotonOptions,
    #[serde(skip_serializing_if = "ManylightOptions::is_empty")]
    pub manylight: ManylightOptions,
    #[serde(skip_serializing_if = "IrradianceOptions::is_empty")]
    pub irradiance: IrradianceOptions,
}

/// `photon`: the photon map (the historygram paper's Pn, Sn, Vn and gather radius).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhotonOptions {
    /// Photon paths traced per progressive pass.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub photons_per_pass: Option<u32>,
    /// Passes the map holds; the picture converges after them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub passes: Option<u32>,
    /// Most scattering events of a photon path (1: single scattering); Russian roulette ends
    /// most paths before it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bounces: Option<u32>,
    /// Gather radius of the first pass in world units (the volume's longest side is 1); 0: 1.5
    /// voxel edges, at least 1/150 of the longest side. Later passes shrink it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius: Option<f32>,
    /// View-ray segments per pixel (Vn).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub segments: Option<u32>,
    /// How a TF edit finds the segments to gather again.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub invalidation: Option<PhotonInvalidation>,
    /// Progressive radius reduction: pass i gathers with r_i, r_i³ = r_0³ · Π_{k<i} (k + α) /
    /// (k + 1) (Knaus & Zwicker); 1 keeps one radius (the paper).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius_alpha: Option<f32>,
    /// Russian roulette: a path goes on past its first scattering with this probability (its
    /// power divided by it); 1 turns it off (every path runs to `bounces`, the paper).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roulette_survival: Option<f32>,
}

/// `photon`: how segments learn that photons within their reach changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhotonInvalidation {
    /// Any changed photon makes every segment stale.
    AnyPhoton,
    /// The paper's 3 × 64-bit spatial historygram.
    Spatial3x64,
    /// A dirty bit per half-size hash cell (the default).
    DirtyCells,
}

/// `manylight`: virtual spherical lights and their shadow maps.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ManylightOptions {
    /// Virtual lights stored.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub virtual_lights: Option<u32>,
    /// Most virtual lights one light path leaves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_bounces: Option<u32>,
    /// Adaptive volumetric shadow map texels per cube-face edge.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub face_res: Option<u32>,
    /// Shadow-map nodes per texel.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nodes: Option<u32>,
    /// How the gather finds the transmittance from a virtual light.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub transmittance: Option<Transmittance>,
    /// Radius of a virtual spherical light in world units.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vsl_radius: Option<f32>,
    /// Iterations rendered with one set of virtual lights before an independent new set is
    /// traced (0: one set for the whole picture).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub iterations_per_set: Option<u32>,
}

/// `manylight`: transmittance from a virtual light to a view sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Transmittance {
    /// Shadow-map lookup at the nearest texel.
    AvsmPoint,
    /// Shadow-map lookup interpolated between texels (the default).
    AvsmTrilinear,
    /// A ray marched to the light (the baseline; slow).
    RayMarched,
}

/// `irradiance`: the irradiance cache.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IrradianceOptions {
    /// Use the cache (false: plain Monte Carlo with the same estimator).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cache: Option<bool>,
    /// Which lock a cache miss takes while its entry is created.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub locking: Option<Locking>,
    /// Render image blocks by expected gain instead of in turn.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub priorities: Option<bool>,
    /// Most scattering events on a camera path (1: single scattering).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bounces: Option<u32>,
    /// Largest cache-zone radius in voxels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_radius_voxels: Option<f32>,
    /// γ: accepted relative error of an entry's estimate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gamma: Option<f32>,
    /// ε: accepted relative extrapolation error at a zone's edge.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub epsilon: Option<f32>,
    /// What a TF edit does to the cache.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub invalidation: Option<CacheInvalidation>,
    /// What cache entries hold: the indirect light only (the lights' direct light traced at
    /// every scattering event) or all of it (the paper).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cached_light: Option<CachedLight>,
    /// Scattering events per camera sample along the view ray.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub view_picks: Option<u32>,
}

/// `irradiance`: object-space (octree node) or screen-space (image block) locks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Locking {
    Object,
    Screen,
}

/// `irradiance`: what cache entries hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CachedLight {
    /// The indirect light only (the environment and light the medium scattered); the
    /// directional and point lights' direct light is traced with shadow rays (the default).
    Indirect,
    /// All the light, the lights' direct light included, as the paper.
    All,
}

/// `irradiance`: what a TF edit does to the cache.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CacheInvalidation {
    /// Drop only the entries whose historygrams meet the edit (the default).
    Historygram,
    /// Drop every entry, as the paper does.
    Clear,
}

impl PhotonOptions {
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }
}

impl ManylightOptions {
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }
}

impl IrradianceOptions {
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }
}

/// `a` with every field `b` sets replaced by `b`'s.
macro_rules! overlay {
    ($a:expr, $b:expr, $($field:ident),+) => {
        $( if $b.$field.is_some() { $a.$field = $b.$field; } )+
    };
}

impl TechniqueOptions {
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// These options with every field `edit` sets taken from `edit` (a `technique` message
    /// changes only what it names).
    pub fn overlaid(mut self, edit: &TechniqueOptions) -> TechniqueOptions {
        let (p, e) = (&mut self.photon, &edit.photon);
        overlay!(
            p,
            e,
            photons_per_pass,
            passes,
            bounces,
            radius,
            segments,
            invalidation,
            radius_alpha,
            roulette_survival
        );
        let (m, e) = (&mut self.manylight, &edit.manylight);
        overlay!(
            m,
            e,
            virtual_lights,
            max_bounces,
            face_res,
            nodes,
            transmittance,
            vsl_radius,
            iterations_per_set
        );
        let (i, e) = (&mut self.irradiance, &edit.irradiance);
        overlay!(
            i,
            e,
            cache,
            locking,
            priorities,
            bounces,
            max_radius_voxels,
            gamma,
            epsilon,
            invalidation,
            cached_light,
            view_picks
        );
        self
    }
}
