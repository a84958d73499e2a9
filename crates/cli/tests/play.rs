//! `flowmimic play` with the shipped model: the WebSocket protocol from a Rust client, and the
//! page in headless Chromium driven through the DevTools protocol (keys pressed as a user
//! presses them). Without Chromium (`make test` installs Debian's), the browser part is skipped
//! with a message.

mod common;

use base64::Engine;
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tungstenite::{Message, WebSocket, stream::MaybeTlsStream};

type Socket = WebSocket<MaybeTlsStream<TcpStream>>;

const MODEL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../pretrained/models/fm-walk");
/// The guidance model, with inverse dynamics.
const GUIDANCE_MODEL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../pretrained/models/fm");

/// A child process killed when the test ends, passed or not.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `flowmimic play` on a free port: the process and its `host:port`.
fn start_play(dir: &std::path::Path, model: &str, extra: &[&str]) -> (Killed, String) {
    let args = [&["play", "--model", model, "--port", "0", "--record-dir", "rec"][..], extra].concat();
    let mut server = common::command(dir, &args).stdout(Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(server.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url = line.split_whitespace().nth(1).unwrap_or_else(|| panic!("no address printed: {line}"));
    (Killed(server), url.trim_start_matches("http://").trim_end_matches('/').to_string())
}

fn connect(host: &str) -> Socket {
    let (socket, _) = tungstenite::connect(format!("ws://{host}/ws")).unwrap();
    socket
}

/// The next message of `kind` (frames keep coming between the others).
fn next_of(socket: &mut Socket, kind: &str) -> Value {
    for _ in 0..200 {
        if let Message::Text(t) = socket.read().unwrap() {
            let m: Value = serde_json::from_str(t.as_str()).unwrap();
            if m["type"] == kind {
                return m;
            }
        }
    }
    panic!("no '{kind}' message in 200");
}

/// One GET: the status line and the body (read to its Content-Length: Chromium's DevTools
/// server keeps the connection open).
fn http_get(host: &str, path: &str, host_header: &str) -> (String, String) {
    let mut stream = TcpStream::connect(host).unwrap();
    write!(stream, "GET {path} HTTP/1.1\r\nHost: {host_header}\r\nConnection: close\r\n\r\n").unwrap();
    let mut reader = BufReader::new(stream);
    let (mut status, mut line, mut length) = (String::new(), String::new(), 0);
    reader.read_line(&mut status).unwrap();
    while reader.read_line(&mut line).unwrap() > 2 {
        if let Some((name, value)) = line.split_once(':')
            && name.eq_ignore_ascii_case("content-length")
        {
            length = value.trim().parse().unwrap();
        }
        line.clear();
    }
    let mut body = vec![0; length];
    reader.read_exact(&mut body).unwrap();
    (status, String::from_utf8(body).unwrap())
}

#[test]
fn live_play_speaks_its_protocol_and_survives_bad_clients() {
    let dir = common::workdir("play-protocol");
    let (_server, host) = start_play(&dir, MODEL, &[]);
    // An idle connection blocks nobody; a foreign Host or Origin is refused.
    let _idle = TcpStream::connect(&host).unwrap();
    assert!(http_get(&host, "/", &host).0.starts_with("HTTP/1.1 200"));
    assert!(http_get(&host, "/", "evil.example").0.starts_with("HTTP/1.1 403"));
    let mut foreign = tungstenite::client::IntoClientRequest::into_client_request(format!("ws://{host}/ws")).unwrap();
    foreign.headers_mut().insert("Origin", "https://evil.example".parse().unwrap());
    assert!(tungstenite::connect(foreign).is_err(), "a page from elsewhere opened the socket");

    let mut socket = connect(&host);
    let hello = next_of(&mut socket, "hello");
    assert_eq!(hello["names"].as_array().unwrap().len(), 24, "{hello}");
    let frame = next_of(&mut socket, "frame");
    assert_eq!(frame["bodies"].as_array().unwrap().len(), 24, "{frame}");
    // The loop's own budget with no browser on the cores (printed, not asserted).
    let later = (0..60).map(|_| next_of(&mut socket, "frame")).last().unwrap();
    eprintln!(
        "model {} ms, physics {} ms, {} steps in the last second",
        later["model_ms"], later["physics_ms"], later["rate"]
    );
    // Malformed, unknown, out-of-range and oversized messages each get an error; frames go on.
    let oversized = format!("{{\"type\":\"push\",\"pad\":\"{}\"}}", "x".repeat(5000));
    for (message, why) in [
        ("not json", "bad message"),
        (r#"{"type":"fly"}"#, "unknown variant"),
        (r#"{"type":"drive","vx":40,"vy":0,"yaw_rate":0}"#, "joystick speed"),
        (r#"{"type":"sampler","scale":1,"nfe":0}"#, "NFE"),
        (oversized.as_str(), "limit"),
    ] {
        socket.send(Message::text(message)).unwrap();
        let error = next_of(&mut socket, "error");
        assert!(error["message"].as_str().unwrap().contains(why), "{message:.40}: {error}");
    }
    socket.send(Message::binary(vec![0u8; 8])).unwrap();
    assert!(next_of(&mut socket, "error")["message"].as_str().unwrap().contains("binary"));
    // A command is applied by the next control step, and echoed with its sequence number.
    socket.send(Message::text(r#"{"type":"drive","vx":0.8,"vy":0,"yaw_rate":0.3,"seq":42}"#)).unwrap();
    let applied = (0..10).map(|_| next_of(&mut socket, "frame")).find(|f| f["applied"] == 42).expect("applied");
    assert_eq!(applied["command"], json!([0.8, 0.0, 0.3]), "{applied}");
    // This model has no inverse dynamics: the page is told, and a share for it is refused.
    assert_eq!(hello["inverse_dynamics"], json!(null), "{hello}");
    socket.send(Message::text(r#"{"type":"sampler","scale":30,"nfe":2,"inverse_dynamics":0.25}"#)).unwrap();
    assert!(next_of(&mut socket, "error")["message"].as_str().unwrap().contains("no inverse dynamics"));
    // Recording writes a rollout that the other commands read, with the sampler the page set.
    socket.send(Message::text(r#"{"type":"sampler","scale":12,"nfe":3}"#)).unwrap();
    (0..3).for_each(|_| drop(next_of(&mut socket, "frame")));
    socket.send(Message::text(r#"{"type":"record"}"#)).unwrap();
    (0..10).for_each(|_| drop(next_of(&mut socket, "frame")));
    socket.send(Message::text(r#"{"type":"record"}"#)).unwrap();
    let notice = next_of(&mut socket, "notice");
    let path = notice["message"].as_str().unwrap().split(" to ").nth(1).expect("a path").to_string();
    assert!(path.ends_with(".rollout.safetensors"), "{notice}");
    let rollout = flowmimic_control::Rollout::load(&dir.join(&path)).unwrap();
    assert!(rollout.envs == 1 && rollout.steps >= 9 && rollout.survived == [rollout.steps], "{notice}");
    assert_eq!((rollout.info.guidance_scale, rollout.info.nfe), (12.0, 3), "{notice}");
    // A client past the transport limit is dropped; the session serves the next one.
    socket.send(Message::text("y".repeat(100_000))).ok();
    drop(socket);
    let mut again = connect(&host);
    next_of(&mut again, "frame");
    std::fs::remove_dir_all(&dir).ok();
}

fn chromium() -> Option<&'static str> {
    ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find(|b| Command::new(b).arg("--version").output().is_ok_and(|o| o.status.success()))
}

/// A DevTools-protocol connection to one page.
struct Page {
    socket: Socket,
    id: u64,
}

impl Page {
    fn call(&mut self, method: &str, params: Value) -> Value {
        self.id += 1;
        self.socket
            .send(Message::text(json!({"id": self.id, "method": method, "params": params}).to_string()))
            .unwrap();
        loop {
            if let Message::Text(t) = self.socket.read().unwrap() {
                let m: Value = serde_json::from_str(t.as_str()).unwrap();
                if m["id"] == self.id {
                    assert!(m.get("error").is_none(), "{method}: {m}");
                    return m["result"].clone();
                }
            }
        }
    }

    fn eval(&mut self, expression: &str) -> Value {
        self.call("Runtime.evaluate", json!({"expression": expression, "returnByValue": true}))["result"]["value"]
            .clone()
    }

    /// A left click on the ground at world `(x, y)`, where the page draws it, which must be on
    /// the canvas and not under a panel.
    fn click_ground(&mut self, x: f64, y: f64) {
        let at = self.eval(&format!(
            "(() => {{ const s = play.screenOf([{x}, {y}, 0]), e = document.elementFromPoint(s[0], s[1]); \
             return [s[0], s[1], e && e.id]; }})()"
        ));
        let (px, py) = (at[0].as_f64().unwrap(), at[1].as_f64().unwrap());
        assert_eq!(at[2], json!("gl"), "({x:.2}, {y:.2}) shows at pixel ({px:.0}, {py:.0}), not on the open canvas");
        for kind in ["mouseMoved", "mousePressed", "mouseReleased"] {
            self.mouse(kind, px, py);
        }
    }

    /// One mouse event of the left button at page pixel `(x, y)`.
    fn mouse(&mut self, kind: &str, x: f64, y: f64) {
        let params = json!({"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1});
        self.call("Input.dispatchMouseEvent", params);
    }

    /// Orbits the camera by dragging the mouse across the canvas, as a user does, until it looks
    /// along `heading` (rad): the page turns the view 0.008 rad per pixel dragged.
    fn look_along(&mut self, heading: f64) {
        let yaw = self.eval("cam.yaw").as_f64().unwrap();
        let pixels = flowmimic_geom::wrap_angle(yaw - heading - std::f64::consts::PI) / 0.008;
        if pixels.abs() < 4.0 {
            return; // a shorter drag is a click
        }
        // From the middle of the page, where the humanoid stands on the canvas.
        let centre = self
            .eval("[innerWidth / 2, innerHeight / 2, document.elementFromPoint(innerWidth / 2, innerHeight / 2).id]");
        assert_eq!(centre[2], json!("gl"), "the middle of the page is not the canvas");
        let (x, y) = (centre[0].as_f64().unwrap(), centre[1].as_f64().unwrap());
        self.mouse("mousePressed", x, y);
        for i in 1..=10 {
            self.mouse("mouseMoved", x + pixels * f64::from(i) / 10.0, y);
        }
        self.mouse("mouseReleased", x + pixels, y);
    }

    fn key(&mut self, kind: &str, code: &str, key: &str, vk: u32) {
        let params = json!({"type": kind, "code": code, "key": key, "windowsVirtualKeyCode": vk});
        self.call("Input.dispatchKeyEvent", params);
    }

    /// Polls `expression` every 50 ms until it is true, up to `seconds`.
    fn wait_for(&mut self, expression: &str, seconds: f64) -> bool {
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < seconds {
            if self.eval(expression) == json!(true) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        false
    }

    /// Simulated seconds from now until the walker's achieved `axis` speed (0 forward, 1 left),
    /// averaged over the last 0.5 s of streamed frames, is below `below` m/s; `None` when it is
    /// not within `limit` s (nor within twice that of wall time, should the stream stall).
    fn seconds_until_slower(&mut self, axis: usize, below: f64, limit: f64) -> Option<f64> {
        let start = self.eval("play.frame.time").as_f64().unwrap();
        let wall = Instant::now();
        let mut recent: Vec<(f64, f64)> = Vec::new();
        loop {
            let f = self.eval(&format!("[play.frame.time, play.frame.velocity[{axis}]]"));
            let (t, v) = (f[0].as_f64().unwrap() - start, f[1].as_f64().unwrap());
            if t > limit || wall.elapsed().as_secs_f64() > 2.0 * limit {
                return None;
            }
            recent.push((t, v));
            recent.retain(|&(s, _)| s > t - 0.5);
            if t >= 0.5 && recent.iter().map(|&(_, v)| v).sum::<f64>() / (recent.len() as f64) < below {
                return Some(t);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The mean achieved `axis` speed (0 forward, 1 left; m/s) over `seconds` of streamed frames.
    fn mean_velocity(&mut self, axis: usize, seconds: f64) -> f64 {
        let start = Instant::now();
        let mut speeds = Vec::new();
        while start.elapsed().as_secs_f64() < seconds {
            speeds.push(self.eval(&format!("play.frame.velocity[{axis}]")).as_f64().unwrap());
            std::thread::sleep(Duration::from_millis(50));
        }
        speeds.iter().sum::<f64>() / speeds.len() as f64
    }

    /// Over `seconds` of streamed frames, the mean achieved forward speed and the mean forward
    /// speed of the predicted pelvis path (the sampled plan the page draws), both m/s.
    fn mean_speeds(&mut self, seconds: f64) -> (f64, f64) {
        // Forward is the pelvis heading, from the hips (left hip minus right hip points left).
        const PLANNED: &str = "(() => { const f = play.frame, b = f.bodies, p = f.plan; \
            const l = b[1], r = b[5], yaw = Math.atan2(l[1] - r[1], l[0] - r[0]) - Math.PI / 2; \
            const d = [p[p.length - 1][0] - b[0][0], p[p.length - 1][1] - b[0][1]]; \
            return (Math.cos(yaw) * d[0] + Math.sin(yaw) * d[1]) * 30 / p.length; })()";
        let start = Instant::now();
        let (mut achieved, mut planned) = (Vec::new(), Vec::new());
        while start.elapsed().as_secs_f64() < seconds {
            achieved.push(self.eval("play.frame.velocity[0]").as_f64().unwrap());
            planned.push(self.eval(PLANNED).as_f64().unwrap());
            std::thread::sleep(Duration::from_millis(100));
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        (mean(&achieved), mean(&planned))
    }
}

/// Headless Chromium on the page: the page renders and streams, offers the inverse-dynamics
/// share, W walks forward and S backward within 2 s of the key, D is measured, R resets, and a
/// clicked obstacle is walked around.
#[test]
fn live_play_steers_from_a_real_browser() {
    let Some(browser) = chromium() else {
        eprintln!("SKIPPED: no Chromium here (`make test` installs Debian's `chromium`); the page was not driven");
        return;
    };
    let dir = common::workdir("play-browser");
    // No flag: the model's recommended play settings (a fixed w 30 with a fifth of inverse
    // dynamics), as a user gets them.
    let (_server, host) = start_play(&dir, GUIDANCE_MODEL, &[]);
    let mut chrome = Command::new(browser)
        .args(["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        .args(["--remote-debugging-port=0", "--window-size=1000,700", "--no-first-run"])
        .arg(format!("--user-data-dir={}", dir.join("chrome").display()))
        .arg(format!("http://{host}/"))
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(chrome.stderr.take().unwrap()).lines();
    let _chrome = Killed(chrome);
    let devtools = lines
        .by_ref()
        .map_while(Result::ok)
        .find_map(|l| l.split_once("DevTools listening on ws://").map(|(_, rest)| rest.to_string()))
        .expect("Chromium prints its DevTools address");
    std::thread::spawn(move || lines.for_each(drop));
    let port_host = devtools.split('/').next().unwrap().to_string();
    let targets: Value = serde_json::from_str(&http_get(&port_host, "/json/list", &port_host).1).unwrap();
    let target = targets.as_array().unwrap().iter().find(|t| t["type"] == "page").expect("a page");
    let (socket, _) = tungstenite::connect(target["webSocketDebuggerUrl"].as_str().unwrap()).unwrap();
    let mut page = Page { socket, id: 0 };
    assert!(page.wait_for("window.play !== undefined && play.frames > 30", 30.0), "no frames reached the page");
    assert!(page.eval("play.errors.length") == json!(0), "{}", page.eval("JSON.stringify(play.errors)"));
    // The guidance model has inverse dynamics: the panel offers its share, at the one in force
    // (the model's recommended 0.2).
    let shown = page.eval("[getComputedStyle($('idlabel')).display, $('id').value]");
    assert_eq!(shown, json!(["block", "0.2"]), "the inverse-dynamics slider");

    // The page draws: the screenshot holds the floor, the humanoid and the panels.
    let shot = page.call("Page.captureScreenshot", json!({"format": "png"}));
    let png = base64::engine::general_purpose::STANDARD.decode(shot["data"].as_str().unwrap()).unwrap();
    std::fs::write(dir.join("play.png"), &png).unwrap();
    let mut reader = png::Decoder::new(std::io::Cursor::new(png)).read_info().unwrap();
    let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut pixels).unwrap();
    let colours: std::collections::HashSet<&[u8]> = pixels[..info.buffer_size()].chunks(4).collect();
    assert!(colours.len() > 500, "a blank page: {} colours", colours.len());

    // W: the server applies forward, and the humanoid walks forward; S: backward.
    page.key("keyDown", "KeyW", "w", 87);
    assert!(page.wait_for("play.frame.command[0] === 1", 2.0), "W was not applied");
    let w_latency = page.eval("play.latencyMs");
    page.mean_speeds(1.0);
    let (forward, forward_plan) = page.mean_speeds(3.0);
    page.key("keyUp", "KeyW", "w", 87);
    page.key("keyDown", "KeyS", "s", 83);
    // From the key press, the simulated time until the walker walks back (a 0.5 s mean below
    // -0.1 m/s).
    let reversed = page.seconds_until_slower(0, -0.1, 4.0);
    assert!(page.wait_for("play.frame.command[0] === -0.6", 2.0), "S was not applied");
    let s_latency = page.eval("play.latencyMs");
    page.mean_speeds(1.0);
    let (backward, backward_plan) = page.mean_speeds(3.0);
    // D: a sidestep right at 0.3 m/s, measured and printed, not asserted: the shipped model's
    // data hardly sidesteps (issue 46).
    page.key("keyUp", "KeyS", "s", 83);
    page.key("keyDown", "KeyD", "d", 68);
    let sidestepped = page.seconds_until_slower(1, -0.1, 3.0);
    let sideways = page.mean_velocity(1, 1.5);
    page.key("keyUp", "KeyD", "d", 68);
    page.key("keyDown", "KeyS", "s", 83);
    let budget = page.eval("[play.frame.model_ms, play.frame.physics_ms, play.frame.rate]");
    eprintln!(
        "key -> applied: W {w_latency} ms, S {s_latency} ms; forward speed achieved / planned: \
         W {forward:.2} / {forward_plan:.2} m/s, S {backward:.2} / {backward_plan:.2} m/s; \
         walking back {reversed:?} s after S, sidestepping right {sidestepped:?} s after D \
         (then {sideways:.2} m/s for -0.3 asked); last step: model, physics ms, steps in the \
         last second {budget}"
    );
    // The guidance model with a fifth of inverse dynamics walks forward on W and keeps walking
    // back on S. Measured in 13 runs of this test on 2 cores and CI's one: W 0.73-0.88 m/s, S
    // -0.27 to -0.63 m/s for -0.6 asked; two runs sampled a slow backward plan (-0.15 / -0.18
    // m/s) and walked back at -0.30 / -0.27. The bound on S is the reversal's own (-0.1 m/s)
    // with room for the gait's sway, not a speed the sampler always reaches. R restarts.
    assert!(forward > 0.5 && backward < -0.15, "W: {forward:.2} m/s, S: {backward:.2} m/s");
    // The joystick issue's bar is walking back within 1.5 s of S from a forward walk: measured
    // here 0.97-1.37 s in 16 runs. The assertion leaves room for the sampler's spread.
    assert!(reversed.is_some_and(|t| t <= 2.0), "walking back {reversed:?} s after S");
    let before = page.eval("play.frame.time").as_f64().unwrap();
    page.key("keyDown", "KeyR", "r", 82);
    assert!(page.wait_for(&format!("play.frame.time < {before} - 1"), 2.0), "R did not reset");
    page.key("keyUp", "KeyS", "s", 83);

    // Clicks drop a waypoint 6 m ahead and an obstacle 2.5 m ahead, in the way: the humanoid
    // walks around it to the waypoint without touching it (MuJoCo's contacts, streamed).
    const AHEAD: &str = "(() => { const b = play.frame.bodies, l = b[1], r = b[5]; \
        const yaw = Math.atan2(l[1] - r[1], l[0] - r[0]) - Math.PI / 2; return [b[0][0], b[0][1], yaw]; })()";
    let start = page.eval(AHEAD);
    let [x0, y0, yaw] = [0, 1, 2].map(|i| start[i].as_f64().unwrap());
    let ahead = |d: f64| (x0 + d * yaw.cos(), y0 + d * yaw.sin());
    let ((gx, gy), (ox, oy)) = (ahead(6.0), ahead(2.5));
    // From the default view the ground 6 m ahead can fall under the settings panel.
    page.look_along(yaw);
    page.eval("$('clickmode').value = 'waypoint'");
    page.click_ground(gx, gy);
    assert!(page.wait_for("play.frame.waypoint !== null", 3.0), "the waypoint click was not applied");
    page.eval("$('clickmode').value = 'obstacle'");
    page.click_ground(ox, oy);
    assert!(page.wait_for("play.frame.obstacles.length === 1", 3.0), "the obstacle click was not applied");
    let placed = page.eval("play.frame.obstacles[0].at");
    let (px, py) = (placed[0].as_f64().unwrap(), placed[1].as_f64().unwrap());
    // The camera follows the walker, which has set off toward the waypoint by the time the click
    // lands: within 0.6 m of where it was aimed.
    assert!((px - ox).hypot(py - oy) < 0.6, "the obstacle landed at ({px:.2}, {py:.2}), not ({ox:.2}, {oy:.2})");
    let (mut touched, mut closest, mut passed) = (0, f64::INFINITY, false);
    let started = Instant::now();
    while started.elapsed().as_secs_f64() < 15.0 && !passed {
        let f = page.eval("[play.frame.touching, play.frame.fell, play.frame.bodies[0][0], play.frame.bodies[0][1]]");
        touched += usize::from(f[0] == json!(true));
        assert!(f[1] == json!(false), "the humanoid fell");
        let (x, y) = (f[2].as_f64().unwrap(), f[3].as_f64().unwrap());
        closest = closest.min((x - px).hypot(y - py) - 0.3);
        // Past the obstacle: 1 m beyond it along the way.
        passed = (x - x0) * yaw.cos() + (y - y0) * yaw.sin() > 3.5;
        std::thread::sleep(Duration::from_millis(100));
    }
    eprintln!(
        "around the obstacle: passed {passed}, pelvis's closest approach to its edge {closest:.2} m, {touched} frames touching"
    );
    assert!(passed, "did not get past the obstacle in 15 s");
    assert_eq!(touched, 0, "the humanoid touched the obstacle (pelvis came within {closest:.2} m of its edge)");
    std::fs::remove_dir_all(&dir).ok();
}
