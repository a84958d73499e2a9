//! Offscreen pictures of the humanoid from MuJoCo's own renderer (feature `render`), headless:
//! OpenGL through EGL, which Mesa provides in software on a machine without GPU or display
//! (Debian: `libegl1 libegl-mesa0 libgl1-mesa-dri`).

use crate::SimError;
use crate::humanoid::Humanoid;
use crate::obstacle::{Footprint, Obstacle};
use mujoco_rs::mujoco_c::{mjtGeom, mjv_connector};
use mujoco_rs::prelude::*;
use mujoco_rs::renderer::MjRenderer;
use std::sync::Arc;

/// A decoration drawn into the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Marker {
    /// A sphere (a hand target, a waypoint).
    Sphere { pos: [f64; 3], radius: f64, rgba: [f32; 4] },
    /// An arrow from one point to another (a commanded velocity).
    Arrow { from: [f64; 3], to: [f64; 3], width: f64, rgba: [f32; 4] },
    /// An obstacle where it stands at `time` (s).
    Obstacle { obstacle: Obstacle, time: f64, rgba: [f32; 4] },
}

/// Renders poses of the humanoid with a camera that follows the pelvis.
pub struct Renderer {
    data: MjData<Arc<MjModel>>,
    renderer: MjRenderer,
    pub width: usize,
    pub height: usize,
}

impl Renderer {
    pub fn new(humanoid: &Humanoid, width: usize, height: usize) -> Result<Self, SimError> {
        if width == 0 || height == 0 || width > 1280 || height > 720 {
            return Err(SimError::Render(format!("image size {width}x{height} (1x1 to 1280x720)")));
        }
        let model = Arc::clone(humanoid.model());
        let renderer = MjRenderer::builder()
            .width(width as u32)
            .height(height as u32)
            .num_visual_user_geom(64)
            .build(&model)
            .map_err(|e| {
                SimError::Render(format!(
                    "cannot open an offscreen OpenGL context ({e:?}); headless rendering needs EGL, \
                     on Debian: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri"
                ))
            })?;
        let data = MjData::new(model);
        Ok(Self { data, renderer, width, height })
    }

    /// The RGB image (row-major, top row first) of the humanoid at `qpos` with `markers`.
    pub fn frame(&mut self, qpos: &[f64], markers: &[Marker]) -> Result<&[u8], SimError> {
        if qpos.len() != self.data.qpos().len() || qpos.iter().any(|q| !q.is_finite()) {
            return Err(SimError::Render(format!("invalid pose ({} numbers, or not finite)", qpos.len())));
        }
        self.data.qpos_mut().copy_from_slice(qpos);
        self.data.forward();
        // A free camera (MuJoCo derives its frustum) aimed at the pelvis.
        let camera = self.renderer.camera_mut();
        camera.lookat = [qpos[0], qpos[1], 0.9];
        camera.distance = 4.0;
        camera.azimuth = 135.0;
        camera.elevation = -15.0;
        let scene = self.renderer.user_scene_mut();
        scene.clear_geom();
        for m in markers {
            // SAFETY: decoration geoms with no material, texture or flex/skin object.
            unsafe {
                match *m {
                    Marker::Sphere { pos, radius, rgba } => {
                        scene.create_geom(MjtGeom::mjGEOM_SPHERE, Some([radius; 3]), Some(pos), None, Some(rgba));
                    }
                    Marker::Arrow { from, to, width, rgba } => {
                        let geom = scene.create_geom(MjtGeom::mjGEOM_ARROW, None, None, None, Some(rgba));
                        mjv_connector(geom, mjtGeom::mjGEOM_ARROW as i32, width, &from, &to);
                    }
                    Marker::Obstacle { obstacle: o, time, rgba } => {
                        let [x, y] = o.position(time);
                        let (h, pos) = (o.height / 2.0, Some([x, y, o.height / 2.0]));
                        match o.footprint {
                            Footprint::Cylinder { radius } => {
                                // mjv_initGeom reads a cylinder's size as (radius, half-height).
                                scene.create_geom(
                                    MjtGeom::mjGEOM_CYLINDER,
                                    Some([radius, h, 0.0]),
                                    pos,
                                    None,
                                    Some(rgba),
                                );
                            }
                            Footprint::Box { half, yaw } => {
                                let (s, c) = yaw.sin_cos();
                                let mat = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0];
                                scene.create_geom(
                                    MjtGeom::mjGEOM_BOX,
                                    Some([half[0], half[1], h]),
                                    pos,
                                    Some(mat),
                                    Some(rgba),
                                );
                            }
                        }
                    }
                }
            }
        }
        let err = |e: mujoco_rs::renderer::RendererError| SimError::Render(format!("{e:?}"));
        self.renderer.sync_data(&mut self.data).map_err(err)?;
        self.renderer.render().map_err(err)?;
        self.renderer.rgb_flat().ok_or_else(|| SimError::Render("no RGB buffer".into()))
    }
}
