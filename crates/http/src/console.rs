//! The web console at `/`: plain HTML, CSS and JavaScript under `console/`, embedded in the binary
//! at build time (no CDN, nothing fetched at run time but the API itself). The 3D viewer is
//! three.js, vendored from the npm registry by `scripts/vendor-console.sh`
//! (`console/vendor/PROVENANCE.md`). These are pages, not API operations: they are not in
//! [`super::operations`] nor in `openapi.yaml`, need no API key (the page asks for one and keeps
//! it in memory), and any other path still gets the `not-found` problem.

use axum::Router;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;

/// One embedded file and the path it is served at.
pub struct Asset {
    pub path: &'static str,
    pub content_type: &'static str,
    pub body: &'static [u8],
}

/// Every file of the console.
pub const ASSETS: [Asset; 4] = [
    Asset { path: "/", content_type: "text/html; charset=utf-8", body: include_bytes!("../../../console/index.html") },
    Asset { path: "/console/console.css", content_type: "text/css; charset=utf-8", body: include_bytes!("../../../console/console.css") },
    Asset {
        path: "/console/console.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_bytes!("../../../console/console.js"),
    },
    Asset {
        path: "/console/vendor/viewer.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_bytes!("../../../console/vendor/viewer.js"),
    },
];

/// Scripts, styles and connections from this origin only; photos, the camera and the avatar's
/// texture are `blob:` URLs made by the page.
const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; \
     connect-src 'self' blob: data:; media-src 'self' blob:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

fn respond(asset: &'static Asset) -> Response {
    let mut response = asset.body.into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(asset.content_type));
    headers.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CONTENT_SECURITY_POLICY));
    headers.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    headers.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    // Revalidated on every load: a new binary serves new files at the same paths.
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// The console's routes (GET and HEAD).
pub fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    ASSETS.iter().fold(Router::new(), |router, asset| router.route(asset.path, get(move || async move { respond(asset) })))
}
