//! Pictures of what the humanoid did: a clip or a rollout file rendered by MuJoCo, offscreen,
//! into an animated GIF (no system dependency), an MP4 (through `ffmpeg` when installed) and a
//! contact sheet PNG of key frames. The camera follows the pelvis; a rollout's guidance shows as
//! markers: the hand target (red sphere), the waypoint (green) and the commanded velocity
//! (blue arrow at the feet). `flowmimic view` (crate `flowmimic-serve`) plays the same files in a browser.

use flowmimic_control::Rollout;
use flowmimic_motion::Clip;
use flowmimic_sim::render::{Marker, Renderer};
use flowmimic_sim::{CONTROL_HZ, Humanoid};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

#[derive(Debug, thiserror::Error)]
pub enum VizError {
    #[error(transparent)]
    Sim(#[from] flowmimic_sim::SimError),
    #[error(transparent)]
    File(#[from] flowmimic_io::FileError),
    #[error("{path}: {message}")]
    Output { path: PathBuf, message: String },
}

/// Colour of obstacles in pictures: see-through, so that the humanoid shows behind them.
const OBSTACLE_RGBA: [f32; 4] = [0.45, 0.5, 0.6, 0.55];

/// A sequence of poses at 30 Hz with their markers.
pub struct Frames {
    pub name: String,
    pub qpos: Vec<Vec<f64>>,
    pub markers: Vec<Vec<Marker>>,
}

impl Frames {
    pub fn from_clip(clip: &Clip) -> Self {
        Self { name: clip.name.clone(), qpos: clip.qpos.clone(), markers: vec![Vec::new(); clip.len()] }
    }

    /// Environment `env` of a rollout, up to its fall (and half a second after).
    pub fn from_rollout(r: &Rollout, env: usize, name: &str) -> Self {
        let last = (r.survived[env] + 15).min(r.steps);
        let mut qpos = Vec::with_capacity(last + 1);
        let mut markers = Vec::with_capacity(last + 1);
        for k in 0..=last {
            let q: Vec<f64> = r.qpos(env, k).iter().map(|&x| f64::from(x)).collect();
            let c = r.command(env, k.min(r.steps - 1));
            let task = &r.info.tasks[env];
            let mut m = Vec::new();
            if task.reach.is_some() {
                m.push(Marker::Sphere {
                    pos: [c[3], c[4], c[5]].map(f64::from),
                    radius: 0.06,
                    rgba: [0.9, 0.1, 0.1, 0.9],
                });
            }
            if task.waypoint.is_some() {
                m.push(Marker::Sphere {
                    pos: [f64::from(c[6]), f64::from(c[7]), 0.02],
                    radius: 0.15,
                    rgba: [0.1, 0.8, 0.2, 0.8],
                });
            }
            if !task.joystick.is_empty() && f64::from(c[0]).hypot(f64::from(c[1])) > 1e-3 {
                let yaw = r.heading(env, k);
                let (vx, vy) = (f64::from(c[0]), f64::from(c[1]));
                let to = [q[0] + yaw.cos() * vx - yaw.sin() * vy, q[1] + yaw.sin() * vx + yaw.cos() * vy, 0.05];
                m.push(Marker::Arrow { from: [q[0], q[1], 0.05], to, width: 0.04, rgba: [0.1, 0.3, 0.9, 0.9] });
            }
            let time = k as f64 / CONTROL_HZ;
            m.extend(task.obstacles.iter().map(|&obstacle| Marker::Obstacle { obstacle, time, rgba: OBSTACLE_RGBA }));
            qpos.push(q);
            markers.push(m);
        }
        Self { name: name.to_string(), qpos, markers }
    }
}

/// What a render produced and how long it took.
pub struct Rendered {
    pub frames: usize,
    pub seconds: f64,
    pub files: Vec<PathBuf>,
}

/// Renders `frames` at `fps` (every `30 / fps`-th pose) to `out` (`.gif` or `.mp4`) and a
/// contact sheet of six key frames next to it (`<stem>_sheet.png`).
pub fn render(
    humanoid: &Humanoid,
    frames: &Frames,
    out: &Path,
    size: (usize, usize),
    fps: usize,
) -> Result<Rendered, VizError> {
    let started = Instant::now();
    let (w, h) = size;
    let mut renderer = Renderer::new(humanoid, w, h)?;
    let stride = ((CONTROL_HZ as usize) / fps.clamp(1, 30)).max(1);
    let picked: Vec<usize> = (0..frames.qpos.len()).step_by(stride).collect();
    let mut images = Vec::with_capacity(picked.len());
    for &k in &picked {
        images.push(renderer.frame(&frames.qpos[k], &frames.markers[k])?.to_vec());
    }
    let rate = CONTROL_HZ as usize / stride;
    let bad = |m: String| VizError::Output { path: out.to_path_buf(), message: m };
    let bytes = match out.extension().and_then(|e| e.to_str()) {
        Some("gif") => gif_bytes(&images, w, h, rate).map_err(|e| bad(e.to_string()))?,
        Some("mp4") => mp4_bytes(&images, w, h, rate).map_err(bad)?,
        _ => return Err(bad("choose a .gif or .mp4 output".into())),
    };
    flowmimic_io::write_atomic(out, &bytes)?;
    let sheet = out.with_file_name(format!("{}_sheet.png", out.file_stem().unwrap_or_default().to_string_lossy()));
    let keys: Vec<&[u8]> = (0..6).map(|i| images[i * (images.len() - 1) / 5].as_slice()).collect();
    flowmimic_io::write_atomic(&sheet, &contact_sheet(&keys, w, h).map_err(|e| bad(e.to_string()))?)?;
    Ok(Rendered {
        frames: images.len(),
        seconds: started.elapsed().as_secs_f64(),
        files: vec![out.to_path_buf(), sheet],
    })
}

fn gif_bytes(images: &[Vec<u8>], w: usize, h: usize, fps: usize) -> Result<Vec<u8>, gif::EncodingError> {
    let mut out = Vec::new();
    {
        let mut enc = gif::Encoder::new(&mut out, w as u16, h as u16, &[])?;
        enc.set_repeat(gif::Repeat::Infinite)?;
        for img in images {
            let mut frame = gif::Frame::from_rgb_speed(w as u16, h as u16, img, 20);
            frame.delay = (100 / fps.max(1)) as u16;
            enc.write_frame(&frame)?;
        }
    }
    Ok(out)
}

/// H.264 through the system's `ffmpeg` (Debian: `apt-get install ffmpeg`), as a fragmented
/// MP4 written to a pipe: no temporary file anywhere.
fn mp4_bytes(images: &[Vec<u8>], w: usize, h: usize, fps: usize) -> Result<Vec<u8>, String> {
    let mut child = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", &format!("{w}x{h}")])
        .args(["-r", &fps.to_string(), "-i", "-", "-pix_fmt", "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
        .args(["-f", "mp4", "-movflags", "frag_keyframe+empty_moov", "pipe:1"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .map_err(|e| format!("MP4 needs ffmpeg on the PATH ({e}); write a .gif instead, or apt-get install ffmpeg"))?;
    let mut stdin = child.stdin.take().expect("piped");
    let mut stdout = child.stdout.take().expect("piped");
    // Feed the frames from another thread while this one drains the output, so neither pipe
    // fills up and blocks the other.
    let (bytes, fed) = std::thread::scope(|scope| {
        let feeder = scope.spawn(move || images.iter().try_for_each(|img| stdin.write_all(img)));
        let mut bytes = Vec::new();
        let read = std::io::Read::read_to_end(&mut stdout, &mut bytes);
        (read.map(|_| bytes), feeder.join().unwrap_or(Ok(())))
    });
    let status = child.wait().map_err(|e| format!("ffmpeg: {e}"))?;
    if !status.success() {
        return Err(format!("ffmpeg failed ({status})"));
    }
    fed.map_err(|e| format!("ffmpeg input: {e}"))?;
    bytes.map_err(|e| format!("ffmpeg output: {e}"))
}

/// Six images in a 3 x 2 grid, as PNG.
fn contact_sheet(images: &[&[u8]], w: usize, h: usize) -> Result<Vec<u8>, png::EncodingError> {
    let (cols, rows) = (3, 2);
    let mut sheet = vec![255u8; cols * w * rows * h * 3];
    for (i, img) in images.iter().enumerate() {
        let (cx, cy) = (i % cols, i / cols);
        for y in 0..h {
            let dst = ((cy * h + y) * cols * w + cx * w) * 3;
            sheet[dst..dst + w * 3].copy_from_slice(&img[y * w * 3..(y + 1) * w * 3]);
        }
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, (cols * w) as u32, (rows * h) as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.write_header()?.write_image_data(&sheet)?;
    }
    Ok(out)
}
