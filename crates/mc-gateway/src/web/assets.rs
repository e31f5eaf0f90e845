//! The page's files (`crates/mc-gateway/web/`), compiled into the binary: no CDN, no build step,
//! nothing to install next to the gateway. Their total size is held to [`BUDGET`] by a test, so the
//! page stays quick to load from a Raspberry Pi over a lab network.

use std::sync::Arc;

use axum::{
    http::header,
    response::{IntoResponse, Response},
    routing::get,
    Router,
};

use super::api::App;

/// One embedded file.
pub struct Asset {
    /// Where it is served.
    pub path: &'static str,
    /// Its media type.
    pub content_type: &'static str,
    /// Its bytes.
    pub body: &'static str,
}

/// Every file of the page.
pub const ASSETS: [Asset; 3] = [
    Asset {
        path: "/",
        content_type: "text/html; charset=utf-8",
        body: include_str!("../../web/index.html"),
    },
    Asset {
        path: "/island.css",
        content_type: "text/css; charset=utf-8",
        body: include_str!("../../web/island.css"),
    },
    Asset {
        path: "/island.js",
        content_type: "text/javascript; charset=utf-8",
        body: include_str!("../../web/island.js"),
    },
];

/// The most the page's files may weigh together, bytes.
pub const BUDGET: usize = 200 * 1024;

/// Only the page's own files run: no inline script, nothing from elsewhere.
const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; img-src 'self' data:; \
     frame-ancestors 'none'; base-uri 'none'; form-action 'none'";

fn serve(asset: &'static Asset) -> Response {
    (
        [
            (header::CONTENT_TYPE, asset.content_type),
            // A new gateway version must not be shown with an old page.
            (header::CACHE_CONTROL, "no-cache"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
            (header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY),
        ],
        asset.body,
    )
        .into_response()
}

/// A route per file.
pub fn routes() -> Router<Arc<App>> {
    ASSETS.iter().fold(Router::new(), |router, asset| {
        router.route(asset.path, get(move || async move { serve(asset) }))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_fits_its_budget() {
        let total: usize = ASSETS.iter().map(|a| a.body.len()).sum();
        assert!(
            total <= BUDGET,
            "the page's files weigh {total} bytes; the budget is {BUDGET}"
        );
        assert!(
            total > 5_000,
            "the page's files are suspiciously small: {total} bytes"
        );
    }

    /// The page loads its files by the paths they are served at, and from nowhere else.
    #[test]
    fn the_page_names_its_files_and_nothing_remote() {
        let html = ASSETS[0].body;
        for asset in &ASSETS[1..] {
            let name = asset.path.trim_start_matches('/');
            assert!(
                html.contains(&format!("\"{name}\"")),
                "index.html does not load {name}"
            );
        }
        for asset in &ASSETS {
            // The SVG namespace is a name, not an address that is fetched.
            let body = asset.body.replace("http://www.w3.org/2000/svg", "");
            for remote in ["http://", "https://", "//cdn"] {
                assert!(
                    !body.contains(remote),
                    "{} loads something remote ({remote})",
                    asset.path
                );
            }
        }
    }
}
