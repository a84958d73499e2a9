//! BVH: the hierarchy, the channels and the frames, parsed without ever panicking.
//!
//! Any hierarchy and per-joint channel order; position channels on the root only or on every
//! joint (their values then *replace* the joint's offset, as LAFAN1 writes them); any frame
//! rate; CRLF or LF. Angles are degrees; the local rotation is the product of the rotation
//! channels in the order listed (`Zrotation Yrotation Xrotation` gives `Rz * Ry * Rx`).
//! Lengths stay in the file's units; [`crate::landmarks`] detects them.

use flowmimic_geom::{DQuat, DVec3};

/// A parse error with the 1-based line it refers to.
#[derive(Debug, thiserror::Error)]
#[error("line {line}: {message}")]
pub struct BvhError {
    pub line: usize,
    pub message: String,
}

fn err<T>(line: usize, message: impl Into<String>) -> Result<T, BvhError> {
    Err(BvhError { line, message: message.into() })
}

/// Limits beyond which a file is refused rather than allocated.
const MAX_JOINTS: usize = 1024;
const MAX_FRAMES: usize = 10_000_000;
const MAX_VALUES: usize = 200_000_000;
const MAX_ABS_VALUE: f64 = 1e7;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channel {
    XPosition,
    YPosition,
    ZPosition,
    XRotation,
    YRotation,
    ZRotation,
}

impl Channel {
    fn parse(token: &str) -> Option<Self> {
        Some(match token.to_ascii_lowercase().as_str() {
            "xposition" => Channel::XPosition,
            "yposition" => Channel::YPosition,
            "zposition" => Channel::ZPosition,
            "xrotation" => Channel::XRotation,
            "yrotation" => Channel::YRotation,
            "zrotation" => Channel::ZRotation,
            _ => return None,
        })
    }
}

#[derive(Clone, Debug)]
pub struct Joint {
    pub name: String,
    pub parent: Option<usize>,
    pub offset: DVec3,
    pub channels: Vec<Channel>,
    /// Index of this joint's first value within a frame.
    pub first_value: usize,
    /// Offset of the End Site below this joint, if any.
    pub end_site: Option<DVec3>,
}

/// A parsed BVH file.
#[derive(Clone, Debug)]
pub struct Bvh {
    pub joints: Vec<Joint>,
    /// Seconds per frame.
    pub frame_time: f64,
    /// Values per frame (the sum of all channel counts).
    pub values_per_frame: usize,
    /// `frames * values_per_frame` numbers.
    pub values: Vec<f64>,
}

struct Tokens<'a> {
    items: Vec<(usize, &'a str)>,
    next: usize,
    last_line: usize,
}

impl<'a> Tokens<'a> {
    fn new(lines: &[(usize, &'a str)]) -> Self {
        let mut items = Vec::new();
        for &(line, text) in lines {
            // Braces may touch names ("Hips{"), so split them off.
            let mut start = None;
            for (i, c) in text.char_indices() {
                let brace = c == '{' || c == '}';
                if c.is_whitespace() || brace {
                    if let Some(s) = start.take() {
                        items.push((line, &text[s..i]));
                    }
                    if brace {
                        items.push((line, &text[i..i + 1]));
                    }
                } else if start.is_none() {
                    start = Some(i);
                }
            }
            if let Some(s) = start {
                items.push((line, &text[s..]));
            }
        }
        let last_line = lines.last().map_or(1, |l| l.0);
        Self { items, next: 0, last_line }
    }

    fn next(&mut self, what: &str) -> Result<(usize, &'a str), BvhError> {
        match self.items.get(self.next) {
            Some(&t) => {
                self.next += 1;
                Ok(t)
            }
            None => err(self.last_line, format!("file ends early: expected {what}")),
        }
    }

    fn expect(&mut self, word: &str) -> Result<usize, BvhError> {
        let (line, t) = self.next(&format!("'{word}'"))?;
        if t.eq_ignore_ascii_case(word) { Ok(line) } else { err(line, format!("expected '{word}', found '{t}'")) }
    }

    fn number(&mut self, what: &str) -> Result<f64, BvhError> {
        let (line, t) = self.next(what)?;
        parse_number(line, t, what)
    }
}

fn parse_number(line: usize, token: &str, what: &str) -> Result<f64, BvhError> {
    match token.parse::<f64>() {
        Ok(v) if v.is_finite() && v.abs() <= MAX_ABS_VALUE => Ok(v),
        Ok(v) => err(line, format!("{what} is {v}, outside the plausible range")),
        Err(_) => err(line, format!("{what} '{token}' is not a number")),
    }
}

impl Bvh {
    /// Parses a BVH document.
    pub fn parse(text: &str) -> Result<Self, BvhError> {
        let lines: Vec<(usize, &str)> = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).collect();
        let motion_at = lines.iter().position(|(_, l)| l.eq_ignore_ascii_case("MOTION"));
        let Some(motion_at) = motion_at else {
            return err(lines.len().max(1), "no MOTION section: the file is truncated or not BVH");
        };
        let mut tokens = Tokens::new(&lines[..motion_at]);
        tokens.expect("HIERARCHY")?;
        let mut joints: Vec<Joint> = Vec::new();
        let mut values_per_frame = 0;
        let (line, kw) = tokens.next("ROOT")?;
        if !kw.eq_ignore_ascii_case("ROOT") {
            return err(line, format!("expected 'ROOT', found '{kw}'"));
        }
        Self::parse_joint(&mut tokens, &mut joints, None, &mut values_per_frame)?;
        if let Some(&(line, t)) = tokens.items.get(tokens.next) {
            return err(line, format!("unexpected '{t}' after the hierarchy (only one ROOT is supported)"));
        }
        if values_per_frame == 0 {
            return err(lines[motion_at].0, "the hierarchy has no channels");
        }
        let (values, frame_time) = Self::parse_motion(&lines[motion_at + 1..], values_per_frame)?;
        Ok(Self { joints, frame_time, values_per_frame, values })
    }

    fn parse_joint(
        tokens: &mut Tokens,
        joints: &mut Vec<Joint>,
        parent: Option<usize>,
        values_per_frame: &mut usize,
    ) -> Result<(), BvhError> {
        let (line, name) = tokens.next("a joint name")?;
        if name == "{" {
            return err(line, "joint has no name");
        }
        if joints.len() >= MAX_JOINTS {
            return err(line, format!("more than {MAX_JOINTS} joints"));
        }
        let index = joints.len();
        joints.push(Joint {
            name: name.to_string(),
            parent,
            offset: DVec3::ZERO,
            channels: Vec::new(),
            first_value: *values_per_frame,
            end_site: None,
        });
        tokens.expect("{")?;
        loop {
            let (line, kw) = tokens.next("'}' closing joint")?;
            match kw.to_ascii_uppercase().as_str() {
                "OFFSET" => {
                    let o = [tokens.number("OFFSET x")?, tokens.number("OFFSET y")?, tokens.number("OFFSET z")?];
                    joints[index].offset = DVec3::from_array(o);
                }
                "CHANNELS" => {
                    let (cline, count) = tokens.next("channel count")?;
                    let n: usize = match count.parse() {
                        Ok(n) if (1..=6).contains(&n) => n,
                        _ => return err(cline, format!("channel count '{count}' must be 1 to 6")),
                    };
                    let mut channels = Vec::with_capacity(n);
                    for k in 0..n {
                        let (l, t) = tokens.next("a channel name")?;
                        match Channel::parse(t) {
                            Some(c) => channels.push(c),
                            None => {
                                return err(l, format!("CHANNELS {n} lists {k} channel names; '{t}' is not a channel"));
                            }
                        }
                    }
                    joints[index].first_value = *values_per_frame;
                    *values_per_frame += n;
                    joints[index].channels = channels;
                }
                "JOINT" => Self::parse_joint(tokens, joints, Some(index), values_per_frame)?,
                "END" => {
                    tokens.expect("Site")?;
                    tokens.expect("{")?;
                    tokens.expect("OFFSET")?;
                    let o = [tokens.number("OFFSET x")?, tokens.number("OFFSET y")?, tokens.number("OFFSET z")?];
                    joints[index].end_site = Some(DVec3::from_array(o));
                    tokens.expect("}")?;
                }
                "}" => return Ok(()),
                _ => return err(line, format!("unexpected '{kw}' in joint '{}'", joints[index].name)),
            }
        }
    }

    fn parse_motion(lines: &[(usize, &str)], values_per_frame: usize) -> Result<(Vec<f64>, f64), BvhError> {
        let mut rows = lines.iter().filter(|(_, l)| !l.is_empty());
        let header = |row: Option<&(usize, &str)>, key: &str| -> Result<(usize, String), BvhError> {
            let Some(&(line, text)) = row else {
                return err(lines.last().map_or(1, |l| l.0), format!("file ends before '{key}'"));
            };
            match text.split_once(':') {
                Some((k, v)) if k.trim().eq_ignore_ascii_case(key) => Ok((line, v.trim().to_string())),
                _ => err(line, format!("expected '{key}: ...', found '{text}'")),
            }
        };
        let (fline, frames) = header(rows.next(), "Frames")?;
        let frames: usize = match frames.parse::<usize>() {
            Ok(n) if n <= MAX_FRAMES && n.saturating_mul(values_per_frame) <= MAX_VALUES => n,
            Ok(n) => return err(fline, format!("{n} frames of {values_per_frame} values is absurdly large")),
            Err(_) => return err(fline, format!("frame count '{frames}' is not a whole number")),
        };
        if frames == 0 {
            return err(fline, "the file has no frames");
        }
        let (tline, time) = header(rows.next(), "Frame Time")?;
        let frame_time = parse_number(tline, &time, "Frame Time")?;
        if !(1e-5..=10.0).contains(&frame_time) {
            return err(tline, format!("Frame Time {frame_time} s is not a plausible frame period"));
        }
        // Reserve for what a header claims only up to a modest size: the frames must be read
        // before a large claim is believed.
        let mut values = Vec::with_capacity(frames.min(10_000) * values_per_frame);
        let mut last_line = tline;
        for (k, &(line, text)) in rows.enumerate() {
            if k >= frames {
                return err(line, format!("more frame lines than the {frames} declared"));
            }
            let before = values.len();
            for token in text.split_whitespace() {
                values.push(parse_number(line, token, "value")?);
            }
            let got = values.len() - before;
            if got != values_per_frame {
                return err(line, format!("frame {k} has {got} values; the channels need {values_per_frame}"));
            }
            last_line = line;
        }
        let read = values.len() / values_per_frame;
        if read < frames {
            return err(last_line, format!("truncated: {frames} frames declared, {read} present"));
        }
        Ok((values, frame_time))
    }

    pub fn frames(&self) -> usize {
        self.values.len() / self.values_per_frame
    }

    /// Drops the first `n` frames (CMU cgspeed files start with an added T-pose frame).
    pub fn drop_frames(&mut self, n: usize) {
        let n = n.min(self.frames());
        self.values.drain(..n * self.values_per_frame);
    }

    /// Index of a joint by exact name.
    pub fn joint(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|j| j.name == name)
    }

    /// World positions and orientations of every joint at `frame`, in the file's units and axes.
    pub fn global_pose(&self, frame: usize) -> (Vec<DVec3>, Vec<DQuat>) {
        let row = &self.values[frame * self.values_per_frame..(frame + 1) * self.values_per_frame];
        let mut rot = vec![DQuat::IDENTITY; self.joints.len()];
        let mut pos = vec![DVec3::ZERO; self.joints.len()];
        for (j, joint) in self.joints.iter().enumerate() {
            let mut local_t = joint.offset;
            let mut local_r = DQuat::IDENTITY;
            for (k, &c) in joint.channels.iter().enumerate() {
                let v = row[joint.first_value + k];
                match c {
                    Channel::XPosition => local_t.x = v,
                    Channel::YPosition => local_t.y = v,
                    Channel::ZPosition => local_t.z = v,
                    Channel::XRotation => local_r *= DQuat::from_rotation_x(v.to_radians()),
                    Channel::YRotation => local_r *= DQuat::from_rotation_y(v.to_radians()),
                    Channel::ZRotation => local_r *= DQuat::from_rotation_z(v.to_radians()),
                }
            }
            // Parents come before children in file order.
            match joint.parent {
                None => {
                    pos[j] = local_t;
                    rot[j] = local_r;
                }
                Some(p) => {
                    pos[j] = pos[p] + rot[p] * local_t;
                    rot[j] = rot[p] * local_r;
                }
            }
        }
        (pos, rot)
    }

    /// Writes the file back out (rotation and position channels as stored).
    pub fn to_text(&self) -> String {
        use std::fmt::Write;
        let mut out = String::from("HIERARCHY\n");
        fn write_joint(bvh: &Bvh, j: usize, depth: usize, out: &mut String) {
            let joint = &bvh.joints[j];
            let pad = "\t".repeat(depth);
            let kw = if joint.parent.is_none() { "ROOT" } else { "JOINT" };
            let o = joint.offset;
            let _ = writeln!(out, "{pad}{kw} {}\n{pad}{{\n{pad}\tOFFSET {} {} {}", joint.name, o.x, o.y, o.z);
            let names: Vec<&str> = joint
                .channels
                .iter()
                .map(|c| match c {
                    Channel::XPosition => "Xposition",
                    Channel::YPosition => "Yposition",
                    Channel::ZPosition => "Zposition",
                    Channel::XRotation => "Xrotation",
                    Channel::YRotation => "Yrotation",
                    Channel::ZRotation => "Zrotation",
                })
                .collect();
            if !names.is_empty() {
                let _ = writeln!(out, "{pad}\tCHANNELS {} {}", names.len(), names.join(" "));
            }
            for child in (0..bvh.joints.len()).filter(|&c| bvh.joints[c].parent == Some(j)) {
                write_joint(bvh, child, depth + 1, out);
            }
            if let Some(e) = joint.end_site {
                let _ = writeln!(out, "{pad}\tEnd Site\n{pad}\t{{\n{pad}\t\tOFFSET {} {} {}\n{pad}\t}}", e.x, e.y, e.z);
            }
            let _ = writeln!(out, "{pad}}}");
        }
        write_joint(self, 0, 0, &mut out);
        let _ = writeln!(out, "MOTION\nFrames: {}\nFrame Time: {}", self.frames(), self.frame_time);
        for row in self.values.chunks(self.values_per_frame) {
            let line: Vec<String> = row.iter().map(|v| format!("{v:.6}")).collect();
            let _ = writeln!(out, "{}", line.join(" "));
        }
        out
    }
}
