//! The local web server of `flowmimic view` (replay a clip or a rollout) and `flowmimic play`
//! (drive the guided controller live): axum on tokio, listening on 127.0.0.1 only.
//!
//! Every route goes through one guard: a Host header that is not a loopback name is refused
//! (DNS rebinding), a WebSocket opened by a page from elsewhere is refused (its Origin), request
//! bodies are capped and an answer must come within a time limit. Each connection is its own
//! task, so an idle or slow client never blocks another.
//!
//! - [`view`]: the replay page and its data;
//! - [`play`]: the live session, its WebSocket protocol and page.

pub mod play;
pub mod view;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request};
use axum::http::StatusCode;
use axum::http::header::{HOST, ORIGIN};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::time::Duration;

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot listen on 127.0.0.1:{port}: {error}")]
    Bind { port: u16, error: std::io::Error },
    #[error("server: {0}")]
    Io(std::io::Error),
    #[error("cannot start live play: {0}")]
    Control(flowmimic_control::ControlError),
}

// By hand rather than `#[from]`, which would make the cause the error's `source()` as well as
// part of its message, and error chains print it twice.
impl From<std::io::Error> for ServeError {
    fn from(e: std::io::Error) -> Self {
        Self::Io(e)
    }
}

impl From<flowmimic_control::ControlError> for ServeError {
    fn from(e: flowmimic_control::ControlError) -> Self {
        Self::Control(e)
    }
}

/// Largest request body, bytes (every route is a GET: anything bigger is not ours).
const MAX_BODY: usize = 16 * 1024;
/// Time to answer a request (a WebSocket's upgrade answers at once; the socket then lives on).
const REQUEST_TIMEOUT: Duration = Duration::from_secs(10);

/// Serves `router` (behind [`guarded`]) on 127.0.0.1:`port` (0: any free port) until the
/// process ends; `on_ready` receives the address once listening.
pub fn serve(router: Router, port: u16, on_ready: impl FnOnce(&str)) -> Result<(), ServeError> {
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind(("127.0.0.1", port))
            .await
            .map_err(|error| ServeError::Bind { port, error })?;
        on_ready(&format!("http://{}/", listener.local_addr()?));
        axum::serve(listener, guarded(router)).await?;
        Ok(())
    })
}

/// `router` behind the loopback, origin, size and time guards.
pub fn guarded(router: Router) -> Router {
    router.layer(axum::middleware::from_fn(guard)).layer(DefaultBodyLimit::max(MAX_BODY))
}

async fn guard(request: Request, next: Next) -> Response {
    let headers = request.headers();
    let header = |name| headers.get(name).and_then(|v| v.to_str().ok());
    let refusal = if !header(HOST).is_some_and(loopback_host) {
        Some("this server answers loopback names only")
    } else if header(ORIGIN).is_some_and(|origin| !loopback_origin(origin)) {
        Some("pages from elsewhere may not connect")
    } else {
        None
    };
    if let Some(why) = refusal {
        return (StatusCode::FORBIDDEN, why).into_response();
    }
    match tokio::time::timeout(REQUEST_TIMEOUT, next.run(request)).await {
        Ok(response) => response,
        Err(_) => (StatusCode::REQUEST_TIMEOUT, "no answer in time").into_response(),
    }
}

/// Whether a Host header names this machine's loopback (any port).
fn loopback_host(host: &str) -> bool {
    let name = match host.rsplit_once(':') {
        Some((name, port)) if !name.is_empty() && port.chars().all(|c| c.is_ascii_digit()) => name,
        _ => host,
    };
    matches!(name, "127.0.0.1" | "localhost" | "[::1]")
}

/// Whether an Origin header is a page served from this machine's loopback.
fn loopback_origin(origin: &str) -> bool {
    origin.strip_prefix("http://").is_some_and(loopback_host)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_loopback_names_are_answered() {
        for host in ["127.0.0.1:8000", "localhost:43011", "localhost", "[::1]:80"] {
            assert!(loopback_host(host), "{host}");
        }
        for host in ["evil.example:8000", "127.0.0.1.evil.example", "10.0.0.1:8000", ""] {
            assert!(!loopback_host(host), "{host}");
        }
        assert!(loopback_origin("http://127.0.0.1:4000") && loopback_origin("http://localhost"));
        for origin in ["https://evil.example", "http://evil.example:4000", "null", "file://"] {
            assert!(!loopback_origin(origin), "{origin}");
        }
    }
}
