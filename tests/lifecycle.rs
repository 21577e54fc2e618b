//! What a router spreading sessions over several processes relies on, end to end: the session
//! limit (`at_capacity`, joins still allowed), `/readyz`, the capacity gauges, the route prefix
//! in `welcome`, and the drain (no new sessions, viewers told and still served, `bye` at the
//! deadline or an early end when the last viewer leaves).

use std::time::{Duration, Instant};

use serde_json::json;
use voxlight_app::ServerConfig;
use voxlight_app::lifecycle::drain;
use voxlight_protocol::{ErrorCode, ServerMessage};
use voxlight_tests::{Client, TestServer};

fn hello(name: &str) -> serde_json::Value {
    json!({"type": "hello", "protocol": 1, "viewport": {"width": 32, "height": 32}, "name": name})
}

fn join(session: &str, name: &str) -> serde_json::Value {
    json!({"type": "hello", "protocol": 1, "session": session, "name": name})
}

fn welcome_of(message: ServerMessage) -> (String, Option<String>) {
    match message {
        ServerMessage::Welcome { session, route, .. } => (session, route),
        other => panic!("expected welcome, got {other:?}"),
    }
}

fn refusal(message: ServerMessage) -> (ErrorCode, String) {
    match message {
        ServerMessage::Error { code, message } => (code, message),
        other => panic!("expected an error, got {other:?}"),
    }
}

async fn config(max_sessions: Option<usize>, route: Option<&str>) -> TestServer {
    TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        grace_period: Some(Duration::from_millis(200)),
        max_sessions,
        route_prefix: route.map(str::to_owned),
        ..Default::default()
    })
    .await
    .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_session_past_capacity_is_refused_and_readiness_follows_the_count() {
    let server = config(Some(1), None).await;
    assert_eq!(server.get("/readyz").await.0, 200);
    assert_eq!(server.metric("voxlight_session_capacity ").await, 1.0);

    let mut first = Client::connect(&server.ws_url()).await.unwrap();
    let (id, route) = welcome_of(first.hello_with(hello("Ada")).await.unwrap());
    assert_eq!(route, None, "no route prefix configured, none sent");
    let (status, body) = server.get("/readyz").await;
    assert_eq!(status, 503, "{body}");
    assert!(body.contains("at_capacity"), "{body}");
    assert_eq!(server.metric("voxlight_sessions_active ").await, 1.0);

    let mut second = Client::connect(&server.ws_url()).await.unwrap();
    let (code, message) = refusal(second.hello_with(hello("Bo")).await.unwrap());
    assert_eq!(code, ErrorCode::AtCapacity);
    assert!(message.contains("capacity"), "{message}");
    assert_eq!(
        server.metric("voxlight_sessions_active ").await,
        1.0,
        "a refused hello holds no place"
    );

    // Joining the existing session adds no GPU state: allowed at capacity.
    let mut joiner = Client::connect(&server.ws_url()).await.unwrap();
    let (joined, _) = welcome_of(joiner.hello_with(join(&id, "Cy")).await.unwrap());
    assert_eq!(joined, id);
    joiner.frame_where(|_| true).await.unwrap();

    // Everyone leaves; after the grace period the place is free again.
    first.close().await;
    joiner.close().await;
    let deadline = Instant::now() + Duration::from_secs(20);
    while server.get("/readyz").await.0 != 200 {
        assert!(Instant::now() < deadline, "readiness never came back");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut third = Client::connect(&server.ws_url()).await.unwrap();
    welcome_of(third.hello_with(hello("Di")).await.unwrap());
    third.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_draining_server_serves_its_sessions_opens_none_and_says_bye_at_the_deadline() {
    let server = config(None, Some("/p/0/")).await;
    let mut viewer = Client::connect(&server.ws_url()).await.unwrap();
    let (id, route) = welcome_of(viewer.hello_with(hello("Ada")).await.unwrap());
    assert_eq!(route.as_deref(), Some("/p/0/"));
    let (_, health) = server.get("/healthz").await;
    assert!(health.contains("\"route\":\"/p/0/\""), "{health}");
    viewer.frame_where(|_| true).await.unwrap();

    let state = server.state.clone();
    let started = Instant::now();
    let draining = tokio::spawn(async move { drain(&state, Duration::from_secs(3)).await });

    match viewer
        .text_where(|m| matches!(m, ServerMessage::Draining { .. }))
        .await
        .unwrap()
    {
        ServerMessage::Draining { seconds_left, .. } => {
            assert!((1..=3).contains(&seconds_left), "{seconds_left}")
        }
        _ => unreachable!(),
    }
    let (status, body) = server.get("/readyz").await;
    assert_eq!(status, 503);
    assert!(body.contains("draining"), "{body}");
    assert_eq!(server.metric("voxlight_draining ").await, 1.0);

    // New sessions are refused; a second viewer still joins and is told too.
    let mut newcomer = Client::connect(&server.ws_url()).await.unwrap();
    let (code, _) = refusal(newcomer.hello_with(hello("Bo")).await.unwrap());
    assert_eq!(code, ErrorCode::Draining);
    let mut joiner = Client::connect(&server.ws_url()).await.unwrap();
    welcome_of(joiner.hello_with(join(&id, "Cy")).await.unwrap());
    joiner
        .text_where(|m| matches!(m, ServerMessage::Draining { .. }))
        .await
        .unwrap();

    // The session is still served: an edit during the drain reaches a frame.
    viewer
        .send_json(json!({"type": "params", "density_scale": 3.0, "g": 0.0}))
        .await
        .unwrap();
    let version = match viewer
        .text_where(|m| matches!(m, ServerMessage::Edited { .. }))
        .await
        .unwrap()
    {
        ServerMessage::Edited { version, .. } => version,
        _ => unreachable!(),
    };
    viewer
        .frame_where(|f| f.meta.scene_version >= version)
        .await
        .unwrap();

    // Viewers stay, so the drain runs to its deadline; then the server stops with `bye`.
    draining.await.unwrap();
    let waited = started.elapsed();
    assert!(
        waited >= Duration::from_millis(2900),
        "drain ended after {waited:?} with viewers connected"
    );
    server.shutdown.cancel();
    match viewer
        .text_where(|m| matches!(m, ServerMessage::Bye { .. }))
        .await
        .unwrap()
    {
        ServerMessage::Bye { reason } => assert!(reason.contains("drained"), "{reason}"),
        _ => unreachable!(),
    }
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_drain_ends_when_the_last_viewer_leaves() {
    let server = config(None, None).await;
    let mut viewer = Client::connect(&server.ws_url()).await.unwrap();
    welcome_of(viewer.hello_with(hello("Ada")).await.unwrap());
    let state = server.state.clone();
    let draining = tokio::spawn(async move { drain(&state, Duration::from_secs(120)).await });
    viewer
        .text_where(|m| matches!(m, ServerMessage::Draining { .. }))
        .await
        .unwrap();
    assert!(!draining.is_finished(), "a viewer is still connected");
    let left = Instant::now();
    viewer.close().await;
    tokio::time::timeout(Duration::from_secs(10), draining)
        .await
        .expect("the drain did not end once nobody was left")
        .unwrap();
    assert!(left.elapsed() < Duration::from_secs(10));
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quiet_viewer_of_a_converged_picture_gets_pings() {
    let server = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        ping_interval: Some(Duration::from_millis(300)),
        ..Default::default()
    })
    .await
    .unwrap();
    let mut viewer = Client::connect(&server.ws_url()).await.unwrap();
    viewer
        .send_json(json!({"type": "hello", "protocol": 1, "viewport": {"width": 32, "height": 32}}))
        .await
        .unwrap();
    viewer.frame_where(|f| f.meta.converged).await.unwrap();
    // Nothing else flows now; pings keep proxies from cutting the connection.
    for _ in 0..2 {
        let waited = viewer.wait_for_ping(Duration::from_secs(10)).await.unwrap();
        assert!(waited < Duration::from_secs(5), "{waited:?}");
    }
    viewer.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_route_prefix_or_zero_capacity_is_refused_at_start() {
    for prefix in ["p/0/", "/p/0", "/p//0/", "/p/<0>/"] {
        let result = TestServer::start_with(ServerConfig {
            route_prefix: Some(prefix.into()),
            ..Default::default()
        })
        .await;
        let error = result.err().map(|e| e.to_string()).unwrap_or_default();
        assert!(error.contains("route prefix"), "{prefix}: {error}");
    }
    let result = TestServer::start_with(ServerConfig {
        max_sessions: Some(0),
        ..Default::default()
    })
    .await;
    assert!(result.is_err());
}
