//! `flowmimic view`: a self-contained page on localhost that plays a clip or a rollout in 3D
//! (orbit camera, timeline, speed, trails, commanded and achieved velocity under the scene).
//! The page (`viewer.html`) is compiled into the binary and fetches nothing from elsewhere;
//! the server answers two paths, `/` and `/data.json`, on 127.0.0.1 only.

use crate::VizError;
use flowmimic_control::Rollout;
use flowmimic_motion::Clip;
use flowmimic_sim::skeleton::BODY_PARENTS;
use flowmimic_sim::state::offset;
use flowmimic_sim::{BODY_NAMES, CONTROL_HZ, NUM_BODIES};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

const PAGE: &str = include_str!("viewer.html");

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
            fell: r.fell(env).then_some(r.survived[env]),
        }
    }
}

/// The response to one request line: status, content type, body.
pub fn respond(request_line: &str, json: &str) -> (&'static str, &'static str, Vec<u8>) {
    let path = request_line.split_whitespace().nth(1).unwrap_or("/");
    match path.split('?').next().unwrap_or("/") {
        "/" | "/index.html" => ("200 OK", "text/html; charset=utf-8", PAGE.as_bytes().to_vec()),
        "/data.json" => ("200 OK", "application/json", json.as_bytes().to_vec()),
        _ => ("404 Not Found", "text/plain", b"not found".to_vec()),
    }
}

/// Largest request (line and headers) read, bytes; connections open at once; seconds a client
/// may take to send its request.
const MAX_REQUEST: u64 = 16 * 1024;
const MAX_CONNECTIONS: usize = 64;
const REQUEST_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);

/// Serves `data` on 127.0.0.1:`port` (0: any free port) until killed; `on_ready` receives
/// the address once listening. Each connection has its own thread, a size limit and a
/// timeout, so an idle or slow client never blocks another; a Host header that is not a
/// loopback name is refused (DNS rebinding).
pub fn serve(data: &ViewData, port: u16, on_ready: impl FnOnce(&str)) -> Result<(), VizError> {
    let json: Arc<str> = serde_json::to_string(data).expect("serialisable").into();
    let listener = TcpListener::bind(("127.0.0.1", port))
        .map_err(|e| VizError::Serve(format!("cannot listen on 127.0.0.1:{port}: {e}")))?;
    let addr = listener.local_addr().map_err(|e| VizError::Serve(e.to_string()))?;
    on_ready(&format!("http://{addr}/"));
    let open = Arc::new(AtomicUsize::new(0));
    for mut stream in listener.incoming().flatten() {
        if open.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
            open.fetch_sub(1, Ordering::SeqCst);
            let _ = reply(&mut stream, "503 Service Unavailable", "text/plain", b"busy");
            continue;
        }
        let (json, open) = (Arc::clone(&json), Arc::clone(&open));
        std::thread::spawn(move || {
            // One bad connection never stops the viewer.
            let _ = handle(stream, &json);
            open.fetch_sub(1, Ordering::SeqCst);
        });
    }
    Ok(())
}

/// Whether a Host header names this machine's loopback (any port).
fn loopback_host(host: &str) -> bool {
    let name = match host.rsplit_once(':') {
        Some((name, port)) if !name.is_empty() && port.chars().all(|c| c.is_ascii_digit()) => name,
        _ => host,
    };
    matches!(name, "127.0.0.1" | "localhost" | "[::1]")
}

fn handle(mut stream: TcpStream, json: &str) -> std::io::Result<()> {
    stream.set_read_timeout(Some(REQUEST_TIMEOUT))?;
    stream.set_write_timeout(Some(REQUEST_TIMEOUT))?;
    let mut reader = BufReader::new(stream.try_clone()?.take(MAX_REQUEST));
    let mut request = String::new();
    reader.read_line(&mut request)?;
    // The headers, up to the blank line; a request that never ends it is refused.
    let (mut header, mut host, mut complete) = (String::new(), None, false);
    while reader.read_line(&mut header)? > 0 {
        if header == "\r\n" || header == "\n" {
            complete = true;
            break;
        }
        if let Some((name, value)) = header.split_once(':')
            && name.eq_ignore_ascii_case("host")
        {
            host = Some(value.trim().to_string());
        }
        header.clear();
    }
    if !complete || !request.ends_with('\n') {
        return reply(&mut stream, "400 Bad Request", "text/plain", b"incomplete or oversized request");
    }
    if !host.as_deref().is_some_and(loopback_host) {
        return reply(&mut stream, "403 Forbidden", "text/plain", b"the viewer answers loopback names only");
    }
    let (status, kind, body) = respond(&request, json);
    reply(&mut stream, status, kind, &body)
}

fn reply(stream: &mut TcpStream, status: &str, kind: &str, body: &[u8]) -> std::io::Result<()> {
    write!(
        stream,
        "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    )?;
    stream.write_all(body)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serves_the_page_and_the_data_and_nothing_else() {
        let (status, kind, body) = respond("GET / HTTP/1.1", "{}");
        assert_eq!((status, kind), ("200 OK", "text/html; charset=utf-8"));
        let page = String::from_utf8(body).unwrap();
        assert!(page.contains("fetch(\"data.json\")") && !page.contains("http://") && !page.contains("https://"));
        assert_eq!(respond("GET /data.json?x=1 HTTP/1.1", "{\"a\":1}").2, b"{\"a\":1}");
        assert_eq!(respond("GET /../etc/passwd HTTP/1.1", "{}").0, "404 Not Found");
    }

    #[test]
    fn only_loopback_names_are_answered() {
        for host in ["127.0.0.1:8000", "localhost:43011", "localhost", "[::1]:80"] {
            assert!(loopback_host(host), "{host}");
        }
        for host in ["evil.example:8000", "127.0.0.1.evil.example", "10.0.0.1:8000", ""] {
            assert!(!loopback_host(host), "{host}");
        }
    }
}
