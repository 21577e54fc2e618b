//! voxlight's rendering engine: the wgpu context, GPU volumes, transfer functions, lights,
//! camera, the rendering techniques and tone mapping. No networking, no async runtime: callers
//! drive it from a render thread.

pub mod brightness;
pub mod camera;
pub mod frame;
pub mod gpu;
pub mod gpu_timer;
pub mod image_stats;
pub mod macrocell;
pub mod passes;
pub mod preview;
pub mod renderer;
pub mod scene;
pub mod scene_gpu;
pub mod shaders;
pub mod technique;
pub mod techniques;
pub mod tf;
pub mod validate;
pub mod volume;

use std::sync::Arc;

pub use gpu::Gpu;
pub use renderer::{Frame, Renderer, session_bytes};
pub use scene::{Change, Scene};
pub use technique::{StepReport, Technique, TechniqueStats};
pub use volume::GpuVolume;

/// Everything that can go wrong in the engine.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("{0}")]
    NoAdapter(String),
    #[error("GPU error: {0}")]
    Gpu(String),
    #[error("the GPU device was lost")]
    DeviceLost,
    #[error("needs {needed} bytes of GPU memory, {available} available")]
    OutOfMemory { needed: u64, available: u64 },
    #[error(
        "a {width}×{height} viewport needs {needed} bytes of GPU buffers; this GPU allows at most {max_pixels} pixels per session"
    )]
    ViewportTooLarge {
        width: u32,
        height: u32,
        needed: u64,
        max_pixels: u64,
    },
    #[error(
        "the server's GPU memory budget is used up: this needs {needed} bytes, {in_use} of {budget} are in use by other sessions; try a smaller viewport or later"
    )]
    MemoryBudget {
        needed: u64,
        in_use: u64,
        budget: u64,
    },
    #[error("unknown technique `{0}`")]
    UnknownTechnique(String),
    #[error("invalid scene: {0}")]
    InvalidScene(String),
}

/// Pipelines shared by every session on one GPU; sessions own only buffers and textures.
pub struct Engine {
    pub gpu: Arc<Gpu>,
    pub raymarch: passes::estimator::EstimatorPass,
    pub pathtrace: passes::estimator::EstimatorPass,
    pub photon: techniques::photon::gpu::PhotonPass,
    pub tonemap: passes::tonemap::TonemapPass,
    pub manylight: techniques::manylight::gpu::ManylightPasses,
    pub irradiance: techniques::irradiance::gpu::IrradiancePasses,
    pub preview: passes::preview::PreviewPasses,
    /// Most GPU bytes one session may allocate (besides the shared volume texture).
    pub session_budget: u64,
}

impl Engine {
    /// Opens the GPU and builds every pipeline.
    pub fn new() -> Result<Self, EngineError> {
        Self::with_gpu(Arc::new(Gpu::new()?))
    }

    pub fn with_gpu(gpu: Arc<Gpu>) -> Result<Self, EngineError> {
        let raymarch = passes::raymarch::new(&gpu);
        let pathtrace = passes::pathtrace::new(&gpu);
        let photon = techniques::photon::gpu::PhotonPass::new(&gpu);
        let tonemap = passes::tonemap::TonemapPass::new(&gpu);
        let manylight = techniques::manylight::gpu::ManylightPasses::new(&gpu);
        let irradiance = techniques::irradiance::gpu::IrradiancePasses::new(&gpu);
        let preview = passes::preview::PreviewPasses::new(&gpu);
        gpu.check()?;
        let session_budget = gpu.limits.max_buffer_size.min(2 << 30);
        Ok(Self {
            gpu,
            raymarch,
            pathtrace,
            photon,
            tonemap,
            manylight,
            irradiance,
            preview,
            session_budget,
        })
    }

    /// Largest width × height a session may render: its buffers must fit the per-session
    /// budget, and the HDR accumulation buffer (16 bytes a pixel) one storage binding.
    pub fn max_viewport_pixels(&self) -> u64 {
        let per_pixel = renderer::session_bytes(2, 1) - renderer::session_bytes(1, 1);
        let by_budget = self
            .session_budget
            .saturating_sub(renderer::session_bytes(1, 1))
            / per_pixel
            + 1;
        let by_binding = self.gpu.limits.max_storage_buffer_binding_size / 16;
        by_budget.min(by_binding)
    }

    /// The techniques this engine offers.
    pub fn techniques(&self) -> Vec<voxlight_protocol::TechniqueInfo> {
        voxlight_protocol::TechniqueKind::ALL
            .into_iter()
            .map(|kind| voxlight_protocol::TechniqueInfo {
                name: kind.name().to_owned(),
                description: techniques::description(kind).to_owned(),
                default_options: techniques::default_options(kind),
            })
            .collect()
    }

    /// Uploads a volume as a 3D texture (shared by every session that views it).
    pub fn upload_volume(
        &self,
        volume: &voxlight_volumes::Volume,
    ) -> Result<Arc<GpuVolume>, EngineError> {
        GpuVolume::upload(&self.gpu, volume).map(Arc::new)
    }

    /// A per-session renderer for `technique` on `volume`.
    pub fn create_renderer(
        &self,
        technique: &str,
        volume: Arc<GpuVolume>,
        scene: &Scene,
    ) -> Result<Renderer, EngineError> {
        Renderer::new(self, technique, volume, scene)
    }
}
