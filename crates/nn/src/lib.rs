//! Neural-network pieces written by hand for the CPU: the PPO experts' actor and critic, and
//! the small denoisers the generative-model tests train.

pub mod mlp;

pub use mlp::{Adam, Mlp, Tape, sgemm_gflops};
