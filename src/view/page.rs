//! The live view's page, embedded in the binary: nothing is fetched at run time, from us or
//! anyone else. Hand-written HTML, CSS and JavaScript (a small Canvas 2D renderer, no
//! library, no build step); `docs/live-view.md` says why. Owns the files only; the server
//! decides the routes.

/// `GET /`
pub const INDEX_HTML: &str = include_str!("page/index.html");
/// `GET /live.js`
pub const LIVE_JS: &str = include_str!("page/live.js");
/// `GET /live.css`
pub const LIVE_CSS: &str = include_str!("page/live.css");
