//! The `raymarch` pass (shaders/raymarch.wgsl): one progressive single-scattering sample per
//! pixel with the estimator bindings (crate::passes::estimator).

use super::estimator::EstimatorPass;
use crate::Gpu;

pub fn new(gpu: &Gpu) -> EstimatorPass {
    EstimatorPass::new(gpu, "raymarch", &crate::shaders::raymarch())
}
