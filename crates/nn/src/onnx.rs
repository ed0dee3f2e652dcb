//! An ONNX network run on one input at a time: by facegate's own kernels ([`ChainNet`]) when the
//! graph is a chain they run, else by `tract` (pure Rust, any graph). What the input is (how a
//! face is aligned and normalised into it) is the caller's: this takes the planes ready.

use std::sync::Arc;

use tract_onnx::prelude::*;

/// tract's result, which [`OnnxNet`] answers with.
pub use tract_onnx::prelude::TractResult;

use crate::chain::ChainNet;
use crate::conv::Arithmetic;

/// What runs the network.
enum Engine {
    /// facegate's own kernels ([`ChainNet`]): networks that are a plain chain of layers.
    Own(ChainNet),
    /// tract: any other graph.
    Tract(Arc<TypedRunnableModel>),
}

/// Which engines [`OnnxNet::compile`] may choose from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EngineChoice {
    /// facegate's kernels when the graph is a chain they run, else tract.
    Auto,
    /// tract only (the reference the own kernels are tested against).
    Tract,
}

/// An ONNX network compiled for one `1 × 3 × side × side` input at a time. `Send + Sync`.
pub struct OnnxNet {
    engine: Engine,
}

impl OnnxNet {
    /// Compiles `bytes` for a `side`-pixel square input on the engine `choice` allows.
    pub fn compile(bytes: &[u8], side: usize, choice: EngineChoice) -> TractResult<OnnxNet> {
        let own = if choice == EngineChoice::Auto { ChainNet::from_onnx(bytes, side) } else { None };
        let engine = match own {
            Some(net) => Engine::Own(net),
            None => Engine::Tract(
                tract_onnx::onnx()
                    .model_for_read(&mut &bytes[..])
                    .and_then(|m| m.with_input_fact(0, f32::fact([1, 3, side, side]).into()))
                    .and_then(|m| m.into_optimized())
                    .and_then(|m| m.into_runnable())?,
            ),
        };
        Ok(OnnxNet { engine })
    }

    /// Lets go of the own kernels' float weights where they compute in integers
    /// ([`ChainNet::release_float_weights`]; tract's are untouched).
    pub fn release_float_weights(&mut self) {
        if let Engine::Own(net) = &mut self.engine {
            net.release_float_weights();
        }
    }

    /// The same network with the own kernels computing in `arithmetic` (tract's are untouched).
    pub fn with_arithmetic(mut self, arithmetic: Arithmetic) -> OnnxNet {
        self.engine = match self.engine {
            Engine::Own(net) => Engine::Own(net.with_arithmetic(arithmetic)),
            tract => tract,
        };
        self
    }

    /// `facegate` when the project's own kernels run the network, `tract` otherwise.
    pub fn engine(&self) -> &'static str {
        match self.engine {
            Engine::Own(_) => "facegate",
            Engine::Tract(_) => "tract",
        }
    }

    /// One run on an input of side `side` given as three planes (channel-first, in the network's
    /// channel order, normalised as it expects): the raw output.
    pub fn run(&self, planes: Vec<f32>, side: usize) -> TractResult<Vec<f32>> {
        let plan = match &self.engine {
            Engine::Own(net) => return Ok(net.forward(&planes)),
            Engine::Tract(plan) => plan,
        };
        let input = tract_ndarray::Array4::from_shape_vec((1, 3, side, side), planes)?.into_tensor();
        let outputs = plan.run(tvec!(input.into()))?;
        let view = outputs[0].try_as_plain_ram()?;
        Ok(view.as_slice::<f32>()?.to_vec())
    }
}
