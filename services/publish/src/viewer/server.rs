//! The viewer's HTTP side: the page, `/api/status`, `/api/rig`, and the WebSockets of
//! trajectory samples and thumbnails, on one small tokio runtime.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::State;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use tokio::sync::broadcast::error::RecvError;

use super::Shared;

/// The page: one self-contained file, no code from elsewhere.
const PAGE: &str = include_str!("../../viewer/index.html");

/// The page may run only its own inline code, and talk only to where it came from.
const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; \
     img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The routes of the viewer.
pub fn router(shared: Arc<Shared>) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/api/status", get(status))
        .route("/api/rig", get(rig))
        .route("/ws/trajectories", get(trajectories_socket))
        .route("/ws/thumbnails", get(thumbnails_socket))
        .with_state(shared)
}

/// Serves `router` on `listener` until the process ends.
pub async fn serve(listener: std::net::TcpListener, shared: Arc<Shared>) -> std::io::Result<()> {
    listener.set_nonblocking(true)?;
    let listener = tokio::net::TcpListener::from_std(listener)?;
    axum::serve(listener, router(shared)).await
}

async fn page(State(shared): State<Arc<Shared>>, headers: HeaderMap) -> Response {
    if let Err(refused) = check_host(&shared, &headers) {
        return refused.into_response();
    }
    (
        [
            (header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY),
            (header::CACHE_CONTROL, "no-store"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        ],
        Html(PAGE),
    )
        .into_response()
}

async fn status(State(shared): State<Arc<Shared>>, headers: HeaderMap) -> Response {
    if let Err(refused) = check_host(&shared, &headers) {
        return refused.into_response();
    }
    ([(header::CACHE_CONTROL, "no-store")], Json(shared.status_json())).into_response()
}

async fn rig(State(shared): State<Arc<Shared>>, headers: HeaderMap) -> Response {
    if let Err(refused) = check_host(&shared, &headers) {
        return refused.into_response();
    }
    match shared.rig_json() {
        Some(rig) => ([(header::CACHE_CONTROL, "no-store")], Json(rig)).into_response(),
        None => (
            StatusCode::SERVICE_UNAVAILABLE,
            Json(serde_json::json!({ "error": "no rig calibration yet: is the pipeline's ingest stage running?" })),
        )
            .into_response(),
    }
}

async fn trajectories_socket(
    State(shared): State<Arc<Shared>>,
    headers: HeaderMap,
    upgrade: WebSocketUpgrade,
) -> Response {
    open_socket(shared, &headers, upgrade, |s| (s.samples.subscribe(), Vec::new()), Message::Text)
}

async fn thumbnails_socket(
    State(shared): State<Arc<Shared>>,
    headers: HeaderMap,
    upgrade: WebSocketUpgrade,
) -> Response {
    // A new page sees every camera at once, not after the next thumbnail.
    open_socket(shared, &headers, upgrade, |s| (s.thumbnails.subscribe(), s.latest_thumbnails()), Message::Binary)
}

/// Upgrades a request that passes [`check_socket`] to a WebSocket fed by the stream
/// `start` subscribes to (after the messages it returns first).
fn open_socket<T: Clone + Send + 'static>(
    shared: Arc<Shared>,
    headers: &HeaderMap,
    upgrade: WebSocketUpgrade,
    start: fn(&Shared) -> (tokio::sync::broadcast::Receiver<T>, Vec<T>),
    message: fn(T) -> Message,
) -> Response {
    if let Err(refused) = check_socket(&shared, headers) {
        return refused.into_response();
    }
    upgrade.on_upgrade(move |socket| async move {
        let (receiver, first) = start(&shared);
        forward(socket, receiver, first, &shared, message).await;
    })
}

/// Sends `first`, then whatever `receiver` gets, to `socket` until either side ends. A
/// client that reads too slowly skips messages: the stream never waits for it.
async fn forward<T: Clone>(
    mut socket: WebSocket,
    mut receiver: tokio::sync::broadcast::Receiver<T>,
    first: Vec<T>,
    shared: &Shared,
    message: fn(T) -> Message,
) {
    shared.clients.fetch_add(1, Ordering::Relaxed);
    for item in first {
        if socket.send(message(item)).await.is_err() {
            shared.clients.fetch_sub(1, Ordering::Relaxed);
            return;
        }
    }
    loop {
        tokio::select! {
            next = receiver.recv() => match next {
                Ok(item) => {
                    if socket.send(message(item)).await.is_err() {
                        break;
                    }
                }
                Err(RecvError::Lagged(_)) => continue,
                Err(RecvError::Closed) => break,
            },
            incoming = socket.recv() => match incoming {
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => break,
                Some(Ok(_)) => {}
            },
        }
    }
    shared.clients.fetch_sub(1, Ordering::Relaxed);
}

/// Refuses a request whose `Host` is not a name of the address served: a page of another
/// site that resolves its own name to 127.0.0.1 (DNS rebinding) must not reach a viewer on
/// loopback.
/// A refused request: its status and why.
type Refusal = (StatusCode, String);

fn check_host(shared: &Shared, headers: &HeaderMap) -> Result<(), Refusal> {
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    if host_allowed(host, shared.address) {
        Ok(())
    } else {
        Err((StatusCode::FORBIDDEN, format!("host {host:?} is not this viewer's address")))
    }
}

/// [`check_host`], and refuses a WebSocket opened by a page of another origin: browsers
/// send `Origin` with every WebSocket and do not apply the same-origin policy to them.
fn check_socket(shared: &Shared, headers: &HeaderMap) -> Result<(), Refusal> {
    check_host(shared, headers)?;
    let origin = headers.get(header::ORIGIN).map(|o| o.to_str().unwrap_or("(not text)"));
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    if origin_allowed(origin, host) {
        Ok(())
    } else {
        tracing::warn!("viewer: refused a WebSocket from origin {origin:?} (served as {host:?})");
        Err((StatusCode::FORBIDDEN, format!("origin {origin:?} may not open this viewer's streams")))
    }
}

/// Whether a request for `host` reaches the viewer at `address`: any host when it listens
/// on every interface or a routable address; only loopback names when on loopback.
pub fn host_allowed(host: Option<&str>, address: SocketAddr) -> bool {
    let Some(host) = host else { return false };
    if !address.ip().is_loopback() {
        return true;
    }
    let name = match host.rsplit_once(':') {
        Some((name, port)) if !name.ends_with(']') || host.starts_with('[') => {
            if port.parse::<u16>().ok() != Some(address.port()) {
                return false;
            }
            name
        }
        _ => host,
    };
    let name = name.trim_start_matches('[').trim_end_matches(']').to_ascii_lowercase();
    name == "localhost"
        || name.ends_with(".localhost")
        || name.parse::<std::net::IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

/// Whether a WebSocket with `origin` may open on a server reached as `host`: no origin (not
/// a browser), or the page's own origin.
pub fn origin_allowed(origin: Option<&str>, host: Option<&str>) -> bool {
    let Some(origin) = origin else { return true };
    let Some(host) = host else { return false };
    let authority = origin.strip_prefix("http://").or_else(|| origin.strip_prefix("https://"));
    authority.is_some_and(|a| a.eq_ignore_ascii_case(host))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_pages_own_origin_opens_a_socket() {
        let host = Some("127.0.0.1:8787");
        assert!(origin_allowed(Some("http://127.0.0.1:8787"), host));
        assert!(origin_allowed(None, host), "clients that are not browsers send no origin");
        assert!(!origin_allowed(Some("http://127.0.0.1:9000"), host), "another port is another origin");
        assert!(!origin_allowed(Some("http://evil.example"), host));
        assert!(!origin_allowed(Some("null"), host), "sandboxed and file:// pages");
        assert!(!origin_allowed(Some("http://127.0.0.1:8787"), None));
    }

    #[test]
    fn a_viewer_on_loopback_answers_only_to_loopback_names_and_its_port() {
        let loopback: SocketAddr = "127.0.0.1:8787".parse().expect("address");
        for host in ["127.0.0.1:8787", "localhost:8787", "LOCALHOST", "[::1]:8787", "viewer.localhost:8787"] {
            assert!(host_allowed(Some(host), loopback), "{host}");
        }
        for host in ["evil.example:8787", "127.0.0.1:9999", "10.0.0.2:8787"] {
            assert!(!host_allowed(Some(host), loopback), "{host}");
        }
        assert!(!host_allowed(None, loopback));
        let everywhere: SocketAddr = "0.0.0.0:8787".parse().expect("address");
        assert!(host_allowed(Some("studio-pc:8787"), everywhere));
    }
}
