//! The passes that are not one technique's: the progressive estimators (`raymarch`,
//! `pathtrace`), the interactive preview and tone mapping — one module per WGSL pass: the
//! pipeline, its bind group layout and the `#[repr(C)]` structs it binds. A technique's own
//! passes live in its folder (`techniques/<t>/gpu.rs`). `builder` makes the wgpu objects of
//! every pass, these and the techniques'.

pub mod builder;
pub mod estimator;
pub mod pathtrace;
pub mod preview;
pub mod raymarch;
pub mod tonemap;

/// Workgroup edge of the 2D image passes (`@workgroup_size(8, 8)`).
pub const TILE: u32 = 8;

/// One compute pass running `pipeline` over a width × height image in TILE² workgroups.
pub(crate) fn dispatch_image(
    encoder: &mut wgpu::CommandEncoder,
    label: &str,
    pipeline: &wgpu::ComputePipeline,
    bind_group: &wgpu::BindGroup,
    (width, height): (u32, u32),
    timestamp_writes: Option<wgpu::ComputePassTimestampWrites>,
) {
    builder::dispatch(
        encoder,
        label,
        pipeline,
        (bind_group, &[]),
        [width.div_ceil(TILE), height.div_ceil(TILE), 1],
        timestamp_writes,
    );
}
