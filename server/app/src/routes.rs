//! HTTP routes: the embedded web client, `/ws`, `/healthz` (liveness), `/readyz` (takes new
//! sessions), `/metrics` and `/api/datasets`.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use axum::Router;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::json;

use crate::AppState;

include!(concat!(env!("OUT_DIR"), "/web_files.rs"));

/// Largest WebSocket message accepted at the transport; larger text messages within this bound
/// get a `too_large` error reply and the connection survives.
const TRANSPORT_MAX_MESSAGE: usize = 1 << 20;

pub fn app(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/", get(|| async { static_file("index.html") }))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/api/datasets", get(datasets))
        .route("/metrics", get(metrics))
        .route("/ws", get(websocket))
        .route(
            "/{file}",
            get(|Path(file): Path<String>| async move { static_file(&file) }),
        )
        .with_state(state)
}

fn content_type(name: &str) -> &'static str {
    match name.rsplit('.').next() {
        Some("html") => "text/html; charset=utf-8",
        Some("js" | "mjs") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("svg") => "image/svg+xml",
        Some("png") => "image/png",
        Some("json") => "application/json",
        Some("ico") => "image/x-icon",
        _ => "application/octet-stream",
    }
}

fn static_file(name: &str) -> Response {
    match WEB_FILES.iter().find(|(file, _)| *file == name) {
        Some((_, bytes)) => (
            [
                (header::CONTENT_TYPE, content_type(name)),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            *bytes,
        )
            .into_response(),
        None => (StatusCode::NOT_FOUND, format!("no such file: {name}")).into_response(),
    }
}

/// Liveness: the process serves. Also names the adapter (a software one flagged) and the load.
async fn healthz(State(state): State<Arc<AppState>>) -> impl IntoResponse {
    axum::Json(json!({
        "status": "ok",
        "adapter": state.adapter,
        "software_renderer": state.software_renderer,
        "version": env!("CARGO_PKG_VERSION"),
        "sessions": state.metrics.sessions_active.load(Ordering::Relaxed),
        "capacity": state.max_sessions,
        "draining": state.draining.is_cancelled(),
        "route": state.route_prefix,
    }))
}

/// Readiness: 200 while a new session would be admitted, 503 when full or draining (a router
/// then sends new sessions elsewhere; this process still serves its own).
async fn readyz(State(state): State<Arc<AppState>>) -> Response {
    let sessions = state.metrics.sessions_active.load(Ordering::Relaxed);
    match crate::lifecycle::readiness(&state) {
        Ok(()) => axum::Json(json!({ "ready": true, "sessions": sessions })).into_response(),
        Err(why) => (
            StatusCode::SERVICE_UNAVAILABLE,
            axum::Json(json!({ "ready": false, "reason": why.as_str(), "sessions": sessions })),
        )
            .into_response(),
    }
}

/// Prometheus text exposition; needs a token when the server has tokens.
async fn metrics(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Err(refusal) = check_access(&state, &headers) {
        return refusal.into_response();
    }
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        state.metrics.render(),
    )
        .into_response()
}

fn check_access(state: &AppState, headers: &HeaderMap) -> Result<(), crate::auth::Refusal> {
    state.access.check(headers).inspect_err(|refusal| {
        tracing::info!(?refusal, "request refused");
        state
            .metrics
            .upgrades_refused
            .fetch_add(1, Ordering::Relaxed);
    })
}

async fn datasets(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Err(refusal) = check_access(&state, &headers) {
        return refusal.into_response();
    }
    axum::Json(json!({
        "datasets": state.catalog.list(),
        "default": state.default_dataset,
    }))
    .into_response()
}

async fn websocket(
    ws: WebSocketUpgrade,
    headers: HeaderMap,
    State(state): State<Arc<AppState>>,
) -> Response {
    // Refused before the upgrade: a plain HTTP 401/403 the client can read.
    if let Err(refusal) = check_access(&state, &headers) {
        return refusal.into_response();
    }
    ws.protocols([crate::auth::SUBPROTOCOL])
        .max_message_size(TRANSPORT_MAX_MESSAGE)
        .max_frame_size(TRANSPORT_MAX_MESSAGE)
        .on_upgrade(move |socket| {
            let tracker = state.tracker.clone();
            tracker.track_future(crate::session::handle_socket(socket, state))
        })
}
