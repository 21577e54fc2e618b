//! The `pathtrace` pass (shaders/pathtrace.wgsl): one unbiased multiple-scattering path per
//! pixel with the estimator bindings (crate::passes::estimator).

use super::estimator::EstimatorPass;
use crate::Gpu;

pub fn new(gpu: &Gpu) -> EstimatorPass {
    EstimatorPass::new(gpu, "pathtrace", &crate::shaders::pathtrace())
}
