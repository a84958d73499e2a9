//! Neural-network pieces written by hand for the CPU: the PPO experts' actor and critic (an
//! MLP), the trajectory model's Transformer, and Adam. Forward and backward passes run on
//! direct AVX2/FMA kernels where the CPU has them and on SGEMM otherwise (weight gradients
//! always), and are checked against finite differences.

mod dense;
pub mod mlp;
mod small;
pub mod transformer;

pub use mlp::{Adam, Mlp, Tape, sgemm_gflops};
pub use transformer::{TensorSlot, Transformer, TransformerConfig};
