//! `flowmimic view`: a self-contained page that plays a clip or a rollout in 3D (orbit camera,
//! timeline, speed, trails, commanded and achieved velocity under the scene). The page
//! (`view.html`) is compiled into the binary and fetches nothing from elsewhere.

use axum::Router;
use axum::http::header;
use axum::response::Html;
use axum::routing::get;
use flowmimic_control::Rollout;
use flowmimic_motion::Clip;
use flowmimic_sim::skeleton::BODY_PARENTS;
use flowmimic_sim::state::offset;
use flowmimic_sim::{BODY_NAMES, CONTROL_HZ, NUM_BODIES, Obstacle};
use std::sync::Arc;

const PAGE: &str = include_str!("view.html");

/// What the page plays, as JSON.
#[derive(serde::Serialize)]
pub struct ViewData {
    name: String,
    fps: f64,
    names: Vec<&'static str>,
    /// Parent body of each body (-1 for the pelvis).
    parents: Vec<i64>,
    /// World positions of the 24 bodies, per frame.
    bodies: Vec<Vec<[f32; 3]>>,
    /// Forward speed of the root in its character frame, per frame (m/s).
    speed: Vec<f32>,
    /// The rollout's commands per frame (see `flowmimic_control::task::COMMAND_DIM`).
    commands: Option<Vec<Vec<f32>>>,
    reach: bool,
    waypoint: bool,
    /// Obstacles (world, where they stand at time 0, and how they move).
    obstacles: Vec<Obstacle>,
    /// Frame of the fall, if any.
    fell: Option<usize>,
}

fn skeleton() -> (Vec<&'static str>, Vec<i64>) {
    (BODY_NAMES.to_vec(), BODY_PARENTS.iter().map(|p| p.map_or(-1, |p| p as i64)).collect())
}

impl ViewData {
    pub fn from_clip(clip: &Clip) -> Self {
        let (names, parents) = skeleton();
        let bodies =
            clip.bodies.iter().map(|b| b.pos.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect()).collect();
        let speed = clip.bodies.iter().map(|b| b.state()[offset::ROOT_VEL]).collect();
        let name = clip.name.clone();
        Self {
            name,
            fps: CONTROL_HZ,
            names,
            parents,
            bodies,
            speed,
            commands: None,
            reach: false,
            waypoint: false,
            obstacles: Vec::new(),
            fell: None,
        }
    }

    /// Environment `env` of a rollout.
    pub fn from_rollout(r: &Rollout, env: usize, name: &str) -> Self {
        let (names, parents) = skeleton();
        let frames = 0..=r.steps;
        let bodies =
            frames.clone().map(|k| (0..NUM_BODIES).map(|b| r.body(env, k, b).map(|x| x as f32)).collect()).collect();
        let speed = frames.map(|k| r.state(env, k)[offset::ROOT_VEL]).collect();
        let commands = Some((0..r.steps).map(|k| r.command(env, k).to_vec()).collect());
        let task = &r.info.tasks[env];
        Self {
            name: format!("{name} (environment {env}, {} NFE {})", r.info.objective.to_uppercase(), r.info.nfe),
            fps: CONTROL_HZ,
            names,
            parents,
            bodies,
            speed,
            commands,
            reach: task.reach.is_some(),
            waypoint: task.waypoint.is_some(),
            obstacles: task.obstacles.clone(),
            fell: r.fell(env).then_some(r.survived[env]),
        }
    }
}

/// The viewer's routes: the page at `/`, the data at `/data.json`.
pub fn router(data: &ViewData) -> Router {
    let json: Arc<str> = serde_json::to_string(data).expect("serialisable").into();
    Router::new().route("/", get(|| async { Html(PAGE) })).route("/index.html", get(|| async { Html(PAGE) })).route(
        "/data.json",
        get(move || async move { ([(header::CONTENT_TYPE, "application/json")], json.to_string()) }),
    )
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_page_fetches_its_data_and_nothing_from_elsewhere() {
        assert!(super::PAGE.contains("fetch(\"data.json\")"));
        assert!(!super::PAGE.contains("http://") && !super::PAGE.contains("https://"));
    }
}
