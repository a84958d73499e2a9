//! What the plan-against-execution examples share: the model directory and numbers from the
//! command line, and guided environments started from the generated straight walk at NFE 2.

use flowmimic_control::{ControlConfig, Controller};
use flowmimic_model::TrajectoryModel;
use flowmimic_motion::{Clip, GaitParams, generate};
use flowmimic_sim::{Humanoid, SimConfig};
use std::error::Error;
use std::path::Path;
use std::sync::Arc;

pub struct Probe {
    pub model: TrajectoryModel,
    humanoid: Arc<Humanoid>,
    clip: Clip,
    args: Vec<String>,
}

impl Probe {
    /// The model named by the first argument; `usage` says what follows it.
    pub fn from_args(usage: &str) -> Result<Self, Box<dyn Error>> {
        let args: Vec<String> = std::env::args().skip(1).collect();
        let model = TrajectoryModel::load(Path::new(args.first().ok_or(format!("usage: MODEL {usage}"))?))?;
        let humanoid = Humanoid::new(SimConfig::default())?;
        let clip = generate(&humanoid, "walk_straight", &GaitParams { duration: 10.0, ..Default::default() })?.0;
        Ok(Self { model, humanoid, clip, args })
    }

    /// The `i`th number after the model, or `default`.
    pub fn number(&self, i: usize, default: f64) -> Result<f64, Box<dyn Error>> {
        Ok(self.args.get(i).map_or(Ok(default), |a| a.parse::<f64>())?)
    }

    /// `envs` environments guided at `w` for `seconds`, executing the share `beta` of inverse
    /// dynamics.
    pub fn controller(&self, envs: usize, w: f64, beta: f64, seconds: f64) -> Result<Controller<'_>, Box<dyn Error>> {
        let config = ControlConfig { inverse_dynamics: beta as f32, ..ControlConfig::new(2, w as f32, seconds) };
        Ok(Controller::new(&self.model, &self.humanoid, &self.clip, envs, &config)?)
    }
}
