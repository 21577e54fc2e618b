//! The interactive preview's two passes (shaders/preview/light.wgsl, shaders/preview/view.wgsl,
//! declarations in shaders/preview/common.wgsl): the light volume, then one composited view ray
//! per preview pixel. Both share one bind group layout: the estimator's scene, volume, TF,
//! lights and macrocells, plus `PreviewParams`, the light volume and the preview image (with
//! its approximate multiple scattering kept apart for the brightness match).

use bytemuck::{Pod, Zeroable};

use super::TILE;
use super::builder::{Binding, Layout, buffer, dispatch, texture};
use crate::Gpu;

/// Matches `PreviewParams` in preview/common.wgsl.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable, PartialEq)]
pub struct PreviewParams {
    pub light_dims: [u32; 3],
    pub channels: u32,
    pub width: u32,
    pub height: u32,
    pub row_offset: u32,
    pub row_stride: u32,
    pub gain: [f32; 3],
    pub multiple: u32,
    pub multiple_weight: [f32; 3],
    pub z_offset: u32,
}

/// Workgroup of the light-volume pass (`@workgroup_size(8, 8, 1)`: one grid plane per layer).
const LIGHT_TILE: u32 = 8;

/// What bindings 0–8 hold: the estimator's scene, volume, TF, lights and macrocells (4 here),
/// `PreviewParams`, the light volume, the image and its multiple scattering.
pub const BINDINGS: [Binding; 9] = {
    use Binding::*;
    [
        Uniform, Volume, Lut, Uniform, Read, Uniform, ReadWrite, ReadWrite, ReadWrite,
    ]
};

pub struct PreviewPasses {
    pub light: wgpu::ComputePipeline,
    pub view: wgpu::ComputePipeline,
    pub layout: Layout,
}

/// The buffers and texture both passes bind.
pub struct PreviewBindings<'a> {
    pub scene: &'a wgpu::Buffer,
    pub volume: &'a wgpu::TextureView,
    pub tf_lut: &'a wgpu::TextureView,
    pub lights: &'a wgpu::Buffer,
    pub cell_max_opacity: &'a wgpu::Buffer,
    pub params: &'a wgpu::Buffer,
    pub light_volume: &'a wgpu::Buffer,
    pub image: &'a wgpu::Buffer,
    pub image_multiple: &'a wgpu::Buffer,
}

impl PreviewPasses {
    pub fn new(gpu: &Gpu) -> Self {
        let layout = Layout::new(gpu, "preview", &BINDINGS);
        let source = crate::shaders::preview;
        Self {
            light: layout.pipeline(
                gpu,
                "preview light volume",
                &source(crate::shaders::PREVIEW_LIGHT),
            ),
            view: layout.pipeline(gpu, "preview view", &source(crate::shaders::PREVIEW_VIEW)),
            layout,
        }
    }

    pub fn bind_group(&self, gpu: &Gpu, b: &PreviewBindings) -> wgpu::BindGroup {
        let entries = [
            buffer(0, b.scene),
            texture(1, b.volume),
            texture(2, b.tf_lut),
            buffer(3, b.lights),
            buffer(4, b.cell_max_opacity),
            buffer(5, b.params),
            buffer(6, b.light_volume),
            buffer(7, b.image),
            buffer(8, b.image_multiple),
        ];
        self.layout.bind_group(gpu, "preview", &entries)
    }

    /// `planes` grid planes of the light volume over `dims` grid points, from `params.z_offset`.
    pub fn encode_light(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        dims: [u32; 3],
        planes: u32,
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        dispatch(
            encoder,
            "preview light volume",
            &self.light,
            (bind_group, &[]),
            [
                dims[0].div_ceil(LIGHT_TILE),
                dims[1].div_ceil(LIGHT_TILE),
                planes,
            ],
            timestamp_writes,
        );
    }

    /// The view rays of `rows` rows (from `params.row_offset`, every `params.row_stride`-th)
    /// of a width-wide preview image.
    pub fn encode_view(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        (width, rows): (u32, u32),
        timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
    ) {
        dispatch(
            encoder,
            "preview view",
            &self.view,
            (bind_group, &[]),
            [width.div_ceil(TILE), rows.div_ceil(TILE), 1],
            timestamp_writes,
        );
    }
}
