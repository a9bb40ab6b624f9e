//! What a request must look like before any handler reads it: a `Host` this daemon answers
//! to (DNS rebinding), `Content-Type: application/json` on control requests, and a body of
//! bounded size that arrives in bounded time, and an `Origin` that is this server's own page
//! or one it names (a page of another site in a local browser). Owns those checks and
//! their limits; tokens stay in `server.rs`, connection timeouts in `connections.rs`.

use super::error;
use axum::extract::{Request, State};
use axum::http::{Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::Response;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

/// Largest request body (bytes): a `move_joints` job of 10 000 six-axis targets fits.
pub const MAX_BODY_BYTES: usize = 1024 * 1024;
/// How long a request's body may take to arrive once its headers have.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(10);
/// Largest WebSocket message (and frame) a live page may send: it sends nothing but a close.
pub const MAX_LIVE_MESSAGE_BYTES: usize = 4096;
/// Most live pages open at once, over all cells: each costs a socket and a frame stream.
pub const MAX_LIVE_PAGES: usize = 32;
/// Longest echo of a client's own input in an error message.
const MAX_ECHO_CHARS: usize = 200;

/// The `Host` values this daemon answers to: any IP address (a rebinding page reaches us
/// only under a name it controls), `localhost`, and the configured names.
#[derive(Clone)]
pub struct HostCheck {
    names: Arc<[String]>,
}

impl HostCheck {
    pub fn new(_bound: SocketAddr, configured: &[String]) -> Self {
        let names: Vec<String> = std::iter::once("localhost".to_string())
            .chain(configured.iter().map(|n| n.to_ascii_lowercase()))
            .collect();
        HostCheck {
            names: names.into(),
        }
    }

    /// Whether a request with `host` (the header's value, port included) may pass.
    pub fn allows(&self, host: &str) -> bool {
        let name = strip_port(host);
        if name.parse::<std::net::IpAddr>().is_ok() {
            return true;
        }
        let name = name.trim_end_matches('.').to_ascii_lowercase();
        self.names.contains(&name)
    }
}

/// The host part of a `Host` value: `[::1]:80` is `::1`, `a.b:80` is `a.b`.
fn strip_port(host: &str) -> &str {
    if let Some(rest) = host.strip_prefix('[') {
        return rest.split_once(']').map_or(rest, |(ip, _)| ip);
    }
    match host.rsplit_once(':') {
        Some((name, port)) if port.bytes().all(|b| b.is_ascii_digit()) => name,
        _ => host,
    }
}

/// Refuses a request whose `Host` is missing or not one of [`HostCheck`]'s with 421.
pub async fn require_known_host(
    State(check): State<HostCheck>,
    request: Request,
    next: Next,
) -> Response {
    let host = request
        .headers()
        .get(header::HOST)
        .and_then(|h| h.to_str().ok());
    match host {
        Some(host) if check.allows(host) => next.run(request).await,
        _ => error(
            StatusCode::MISDIRECTED_REQUEST,
            "unknown Host: this daemon answers to its IP addresses, localhost and the names in \
             [serve] hosts",
        ),
    }
}

/// Whether a request's `Origin` may pass: none (curl, scripts, the Foxglove desktop app as
/// `docs/foxglove.md` says: only browsers send one), the host the request went to (a page
/// this server served), or one of `also`, compared whole (`scheme://host[:port]`, case
/// aside). Browsers send `Origin` on every cross-origin POST and WebSocket handshake and a
/// page cannot change it, so a page of another site is told apart here.
pub fn origin_allowed(headers: &axum::http::HeaderMap, also: &[String]) -> bool {
    let Some(origin) = headers.get(header::ORIGIN) else {
        return true;
    };
    let Ok(origin) = origin.to_str() else {
        return false;
    };
    if also.iter().any(|o| o.eq_ignore_ascii_case(origin)) {
        return true;
    }
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin_host = origin.split_once("://").map_or(origin, |(_, rest)| rest);
    host.is_some_and(|host| host == origin_host)
}

/// Refuses a control request that is not `Content-Type: application/json` with 415: a
/// page on another site can send a "simple" cross-site POST (`text/plain`, a form) without
/// asking, but not JSON. `stop` and `estop` are exempt: they only ever bring a rig to rest,
/// and an operator's bare `curl -X POST .../estop` must work. `reset` has no body and may
/// come without a content type, but not with another one (a form or `text/plain`): it
/// clears a latched fault and moves nothing, and a page of another site is refused by the
/// `Origin` check whatever it sends. A method other than POST reaches no control handler:
/// it passes on to the router's 405.
pub async fn require_json(request: Request, next: Next) -> Response {
    if request.method() != Method::POST {
        return next.run(request).await;
    }
    let path = request.uri().path();
    if path.ends_with("/stop") || path.ends_with("/estop") {
        return next.run(request).await;
    }
    let content_type = request.headers().get(header::CONTENT_TYPE);
    let bare_reset = path.ends_with("/reset") && content_type.is_none();
    let json = content_type
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .is_some_and(|v| v.trim().eq_ignore_ascii_case("application/json"));
    if json || bare_reset {
        next.run(request).await
    } else {
        error(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "control requests need `Content-Type: application/json`",
        )
    }
}

/// The whole body, at most [`MAX_BODY_BYTES`] and within [`BODY_TIMEOUT`]; else the refusal.
pub async fn read_body(request: Request) -> Result<axum::body::Bytes, Response> {
    let body = request.into_body();
    match tokio::time::timeout(BODY_TIMEOUT, axum::body::to_bytes(body, MAX_BODY_BYTES)).await {
        Ok(Ok(bytes)) => Ok(bytes),
        Ok(Err(_)) => Err(error(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("the body must be at most {MAX_BODY_BYTES} bytes"),
        )),
        Err(_) => Err(error(
            StatusCode::REQUEST_TIMEOUT,
            format!(
                "the body did not arrive within {} s",
                BODY_TIMEOUT.as_secs()
            ),
        )),
    }
}

/// `text` cut to [`MAX_ECHO_CHARS`] characters.
pub fn shorten(text: &str) -> String {
    if text.chars().count() <= MAX_ECHO_CHARS {
        text.to_string()
    } else {
        text.chars().take(MAX_ECHO_CHARS).collect::<String>() + "..."
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_are_ips_localhost_and_the_configured_names() {
        let bound: SocketAddr = "127.0.0.1:8080".parse().expect("a valid socket address");
        let check = HostCheck::new(bound, &["Rig.Example".to_string()]);
        for ok in [
            "127.0.0.1:8080",
            "localhost:8080",
            "[::1]:8080",
            "10.0.0.2",
            "rig.example",
            "LOCALHOST",
        ] {
            assert!(check.allows(ok), "{ok}");
        }
        for bad in [
            "attacker.example",
            "attacker.example:8080",
            "localhost.attacker",
            "",
        ] {
            assert!(!check.allows(bad), "{bad}");
        }
    }
    #[test]
    fn origins_pass_when_absent_this_server_or_listed() {
        let headers = |origin: Option<&str>| {
            let mut map = axum::http::HeaderMap::new();
            map.insert(
                header::HOST,
                "127.0.0.1:8765".parse().expect("a header value"),
            );
            if let Some(origin) = origin {
                map.insert(header::ORIGIN, origin.parse().expect("a header value"));
            }
            map
        };
        let also = [
            "https://app.foxglove.dev".to_string(),
            "file://".to_string(),
        ];
        for ok in [
            None,
            Some("http://127.0.0.1:8765"),
            Some("https://app.foxglove.dev"),
            Some("HTTPS://APP.FOXGLOVE.DEV"),
            Some("file://"),
        ] {
            assert!(origin_allowed(&headers(ok), &also), "{ok:?}");
        }
        for bad in [
            "https://attacker.example",
            "null",
            "http://127.0.0.1:1",
            "https://app.foxglove.dev.attacker.example",
        ] {
            assert!(!origin_allowed(&headers(Some(bad)), &also), "{bad}");
            assert!(!origin_allowed(&headers(Some(bad)), &[]), "{bad}");
        }
        assert!(!origin_allowed(
            &headers(Some("https://app.foxglove.dev")),
            &[]
        ));
    }
}
