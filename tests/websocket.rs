//! End to end: the real server on a free port, a scripted WebSocket client, real frames.

use axum::body::Body;
use axum::http::{Request, StatusCode};
use http_body_util::BodyExt;
use serde_json::json;
use tower::ServiceExt;
use voxlight_protocol::{ErrorCode, FrameFormat, ServerMessage};
use voxlight_tests::{Client, Incoming, TestServer, metric, shared_data};

fn assert_error(message: &ServerMessage, expected: ErrorCode) {
    match message {
        ServerMessage::Error { code, message } => {
            assert_eq!(*code, expected, "error message: {message}");
            assert!(!message.is_empty());
        }
        other => panic!("expected an {expected:?} error, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hello_welcome_frames_tf_edit_and_garbage() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = client.hello(Some("phantom:sphere"), 96, 64).await.unwrap();
    let ServerMessage::Welcome {
        dataset,
        techniques,
        state,
        session,
        ..
    } = welcome
    else {
        unreachable!()
    };
    assert_eq!(dataset.name, "phantom:sphere");
    let details = dataset
        .details
        .expect("welcome carries loaded dataset details");
    assert_eq!(details.histogram.len(), 256);
    assert!(techniques.iter().any(|t| t.name == "raymarch"));
    assert_eq!(state.viewport.width, 96);
    assert!(!session.is_empty());

    // A frame at the requested size that is a picture, not a flat colour.
    let first = client.frame_where(|_| true).await.unwrap();
    assert_eq!((first.width, first.height), (96, 64));
    assert_eq!((first.meta.width, first.meta.height), (96, 64));
    assert_eq!(first.meta.technique, "raymarch");
    assert!(
        first.distinct_colors() > 10,
        "frame is flat: {} colours",
        first.distinct_colors()
    );

    // A TF edit: a later frame (of the edited state) differs.
    let reference = client
        .frame_where(|f| f.meta.scene_version == 0)
        .await
        .unwrap();
    client
        .send_json(json!({"type": "tf", "points": [
            {"value": 0.0, "color": [0.1, 0.2, 0.9], "opacity": 0.0},
            {"value": 1.0, "color": [0.1, 0.2, 0.9], "opacity": 0.3}
        ]}))
        .await
        .unwrap();
    let edited = client
        .frame_where(|f| f.meta.scene_version >= 1)
        .await
        .unwrap();
    assert!(
        edited.max_diff(&reference) > 40,
        "TF edit did not change the picture"
    );

    // Garbage: an error reply each, then frames still come for the next edit.
    client.send_text("this is not json".into()).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    client
        .send_json(json!({"type": "warp_drive"}))
        .await
        .unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    client
        .send_json(json!({"type": "viewport", "width": 0, "height": 10}))
        .await
        .unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadValue);
    client
        .send_json(
            json!({"type": "tf", "points": [{"value": 2.0, "color": [1, 1, 1], "opacity": 1}]}),
        )
        .await
        .unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadValue);
    client.send_binary(vec![1, 2, 3]).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    client
        .send_text("x".repeat(voxlight_protocol::MAX_MESSAGE_BYTES + 1))
        .await
        .unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::TooLarge);
    client
        .send_json(json!({"type": "technique", "name": "nope"}))
        .await
        .unwrap();
    assert_error(
        &client.recv_text().await.unwrap(),
        ErrorCode::UnknownTechnique,
    );
    client
        .send_json(json!({"type": "dataset", "name": "nope"}))
        .await
        .unwrap();
    assert_error(
        &client.recv_text().await.unwrap(),
        ErrorCode::UnknownDataset,
    );
    client
        .send_json(json!({"type": "hello", "protocol": 1}))
        .await
        .unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::NotReady);
    // A viewport the protocol allows but this GPU cannot hold is refused before allocation
    // (lavapipe binds at most 128 MiB per storage buffer: 8 Mi pixels of HDR accumulation).
    let max_pixels = server.state.max_viewport_pixels;
    assert!(
        max_pixels >= 1024 * 1024,
        "a 1024² viewport must fit: {max_pixels}"
    );
    if 4096 * 4096 > max_pixels {
        client
            .send_json(json!({"type": "viewport", "width": 4096, "height": 4096}))
            .await
            .unwrap();
        assert_error(&client.recv_text().await.unwrap(), ErrorCode::GpuMemory);
    }

    client
        .send_json(json!({"type": "camera", "eye": [2.0, -1.0, 0.5], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 35}))
        .await
        .unwrap();
    let after = client
        .frame_where(|f| f.meta.scene_version >= 2)
        .await
        .unwrap();
    assert_eq!((after.width, after.height), (96, 64));
    assert!(
        after.max_diff(&edited) > 20,
        "camera edit did not change the picture"
    );

    // A new viewport: frames follow it.
    client
        .send_json(json!({"type": "viewport", "width": 64, "height": 80}))
        .await
        .unwrap();
    let resized = client
        .frame_where(|f| f.meta.scene_version >= 3)
        .await
        .unwrap();
    assert_eq!((resized.width, resized.height), (64, 80));

    client.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn converged_picture_arrives_as_lossless_png_with_stats() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(None, 64, 64).await.unwrap();
    client
        .send_json(json!({"type": "quality", "iterations": 6, "jpeg_quality": 70}))
        .await
        .unwrap();
    let mut saw_jpeg_quality = false;
    let mut saw_stats = false;
    let last = loop {
        match client.recv().await.unwrap() {
            Incoming::Frame(frame) if frame.meta.converged => break frame,
            Incoming::Frame(frame) => {
                assert_eq!(frame.meta.format, FrameFormat::Jpeg);
                assert!(!frame.meta.lossless);
                saw_jpeg_quality |= frame.meta.quality == Some(70);
            }
            Incoming::Text(message) => match *message {
                ServerMessage::Stats(stats) => {
                    saw_stats = true;
                    assert_eq!(stats.technique, "raymarch");
                    assert!(stats.memory_bytes > 0);
                }
                ServerMessage::Viewers { .. } | ServerMessage::Edited { .. } => {}
                other => panic!("unexpected {other:?}"),
            },
        }
    };
    assert_eq!(last.meta.format, FrameFormat::Png);
    assert!(last.meta.lossless);
    assert_eq!(last.meta.iteration, 6);
    assert_eq!(last.meta.target_iterations, 6);
    // A stats message follows the converged frame at once.
    let Incoming::Text(message) = client.recv().await.unwrap() else {
        panic!("no stats after the converged frame")
    };
    let ServerMessage::Stats(stats) = *message else {
        panic!("expected stats, got {message:?}")
    };
    assert!(stats.converged && stats.iteration == 6, "{stats:?}");
    assert!(stats.gpu_ms > 0.0, "GPU time is measured: {stats:?}");
    assert!(saw_stats || saw_jpeg_quality || last.meta.iteration == 6);
    client.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_before_hello_and_bad_hellos_get_errors() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.send_json(json!({"type": "camera", "eye": [0, 0, 2], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 30})).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::NotReady);
    client.send_text("{".into()).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    // Still usable: a proper hello works.
    client.hello(None, 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    client.close().await;

    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client
        .send_json(json!({"type": "hello", "protocol": 99}))
        .await
        .unwrap();
    assert_error(
        &client.recv_text().await.unwrap(),
        ErrorCode::ProtocolVersion,
    );
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client
        .send_json(json!({"type": "hello", "protocol": 1, "dataset": "../../etc/passwd"}))
        .await
        .unwrap();
    assert_error(
        &client.recv_text().await.unwrap(),
        ErrorCode::UnknownDataset,
    );
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_says_bye() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(None, 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    server.shutdown.cancel();
    let bye = client.recv_text().await.unwrap();
    assert!(matches!(bye, ServerMessage::Bye { .. }), "{bye:?}");
    server.stop().await.unwrap();
}

async fn get_json(app: axum::Router, uri: &str) -> (StatusCode, serde_json::Value) {
    let response = app
        .oneshot(Request::get(uri).body(Body::empty()).unwrap())
        .await
        .unwrap();
    let status = response.status();
    let bytes = response.into_body().collect().await.unwrap().to_bytes();
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_routes_list_datasets_and_serve_the_client() {
    let server = TestServer::start_with(voxlight_server::ServerConfig {
        data_dir: Some(shared_data()),
        default_dataset: None,
        preload: true,
        ..Default::default()
    })
    .await
    .unwrap();
    let app = voxlight_server::app(server.state.clone());
    let (status, health) = get_json(app.clone(), "/healthz").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(health["status"], "ok");
    assert!(health["adapter"].as_str().is_some_and(|a| !a.is_empty()));
    let (status, list) = get_json(app.clone(), "/api/datasets").await;
    assert_eq!(status, StatusCode::OK);
    let names: Vec<&str> = list["datasets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["name"].as_str().unwrap())
        .collect();
    for expected in [
        "phantom:sphere",
        "phantom:cornell",
        "ct-chest-lidc",
        "vti/bonsai.vti",
        "nrrd/tooth.nhdr",
    ] {
        assert!(
            names.contains(&expected),
            "{expected} missing from {names:?}"
        );
    }
    assert!(
        !list.to_string().contains("/shared/data"),
        "server paths must not leak to clients"
    );
    let page = app
        .clone()
        .oneshot(Request::get("/").body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(page.status(), StatusCode::OK);
    let missing = app
        .oneshot(Request::get("/nope.js").body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(missing.status(), StatusCode::NOT_FOUND);
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn chest_ct_opens_by_name_with_hounsfield_range_and_spacing() {
    let server = TestServer::start(Some(shared_data())).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = client.hello(Some("ct-chest-lidc"), 64, 64).await.unwrap();
    let ServerMessage::Welcome { dataset, state, .. } = welcome else {
        unreachable!()
    };
    let details = dataset.details.unwrap();
    assert_eq!(details.dims, [512, 512, 128]);
    assert_eq!(details.spacing, [0.78125, 0.78125, 1.0]);
    assert_eq!((details.value_min, details.value_max), (-1000.0, 1766.0));
    assert_eq!(details.units, "HU");
    assert_eq!(details.modality, "CT");
    assert!(!state.tf.points.is_empty(), "a CT gets a default TF");
    let chest = client.frame_where(|_| true).await.unwrap();
    assert!(chest.distinct_colors() > 10);
    // Switching datasets answers with dataset_loaded and keeps streaming.
    client
        .send_json(json!({"type": "dataset", "name": "phantom:cornell"}))
        .await
        .unwrap();
    let loaded = client.recv_text().await.unwrap();
    let ServerMessage::DatasetLoaded { dataset, .. } = loaded else {
        panic!("{loaded:?}")
    };
    assert_eq!(dataset.name, "phantom:cornell");
    client
        .frame_where(|f| f.meta.scene_version >= 1)
        .await
        .unwrap();
    client.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_and_origins_are_checked_before_the_upgrade() {
    let server = TestServer::start_with(voxlight_server::ServerConfig {
        data_dir: None,
        default_dataset: Some("phantom:sphere".into()),
        preload: false,
        access: voxlight_server::auth::Access {
            tokens: vec!["s3cret".into()],
            allowed_origins: vec!["https://viewer.example".into()],
        },
        ..Default::default()
    })
    .await
    .unwrap();
    let url = server.ws_url();
    let host = server.addr.to_string();
    let refused = |r: Result<(Client, Option<String>), u16>| r.err();
    assert_eq!(
        refused(Client::connect_with(&url, &[]).await),
        Some(401),
        "no token"
    );
    assert_eq!(
        refused(Client::connect_with(&url, &[("Authorization", "Bearer guess")]).await),
        Some(401),
        "wrong token"
    );
    let own_origin = format!("http://{host}");
    assert_eq!(
        refused(
            Client::connect_with(
                &url,
                &[
                    ("Authorization", "Bearer s3cret"),
                    ("Origin", "https://evil.example")
                ]
            )
            .await
        ),
        Some(403),
        "foreign origin, even with a valid token"
    );
    // A script with a bearer token.
    let (mut client, _) = Client::connect_with(&url, &[("Authorization", "Bearer s3cret")])
        .await
        .unwrap();
    client.hello(None, 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    client.close().await;
    // A browser page of this server, token in the subprotocol: the server answers `voxlight`.
    let (mut client, protocol) = Client::connect_with(
        &url,
        &[
            ("Origin", own_origin.as_str()),
            ("Sec-WebSocket-Protocol", "voxlight, voxlight.token.s3cret"),
        ],
    )
    .await
    .unwrap();
    assert_eq!(protocol.as_deref(), Some("voxlight"));
    client.hello(None, 32, 32).await.unwrap();
    client.close().await;
    // An allow-listed origin.
    let (client, _) = Client::connect_with(
        &url,
        &[
            ("Origin", "https://viewer.example"),
            ("Authorization", "Bearer s3cret"),
        ],
    )
    .await
    .unwrap();
    client.close().await;
    // The dataset list needs the token too.
    let app = voxlight_server::app(server.state.clone());
    let (status, body) = get_json(app.clone(), "/api/datasets").await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    assert_eq!(body["error"], "unauthorized");
    let authorized = Request::get("/api/datasets")
        .header("Authorization", "Bearer s3cret")
        .body(Body::empty())
        .unwrap();
    assert_eq!(
        app.oneshot(authorized).await.unwrap().status(),
        StatusCode::OK
    );
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_is_rate_limited_and_the_session_survives() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(None, 32, 32).await.unwrap();
    let camera = json!({"type": "camera", "eye": [0.3, -2.4, 0.1], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30});
    let burst = 3 * voxlight_protocol::MAX_MESSAGES_PER_SECOND;
    for _ in 0..burst {
        client.send_json(camera.clone()).await.unwrap();
    }
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::RateLimited);
    // After a pause the session takes edits again and renders them.
    tokio::time::sleep(std::time::Duration::from_secs(2)).await;
    client
        .send_json(json!({"type": "camera", "eye": [2.4, 0.0, 0.2], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30}))
        .await
        .unwrap();
    let accepted = 2 * voxlight_protocol::MAX_MESSAGES_PER_SECOND as u64;
    let frame = client
        .frame_where(|f| f.meta.scene_version > accepted)
        .await
        .unwrap();
    assert_eq!((frame.width, frame.height), (32, 32));
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_count_sessions_frames_errors_and_latency() {
    let server = TestServer::start(None).await.unwrap();
    let app = voxlight_server::app(server.state.clone());
    let scrape = |app: axum::Router| async move {
        let response = app
            .oneshot(Request::get("/metrics").body(Body::empty()).unwrap())
            .await
            .unwrap();
        assert_eq!(response.status(), StatusCode::OK);
        String::from_utf8(
            response
                .into_body()
                .collect()
                .await
                .unwrap()
                .to_bytes()
                .to_vec(),
        )
        .unwrap()
    };
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(Some("phantom:sphere"), 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    client.send_text("garbage".into()).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    client
        .send_json(json!({"type": "camera", "eye": [0.5, -2.3, 0.4], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30}))
        .await
        .unwrap();
    client
        .frame_where(|f| f.meta.scene_version >= 1)
        .await
        .unwrap();

    // The writer counts a frame after its send returns, so the client can see it first: wait
    // (bounded) for the counts to catch up before checking them.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    let mut text = scrape(app.clone()).await;
    while (metric(&text, "voxlight_input_to_frame_seconds_count ") < 1.0
        || metric(&text, "voxlight_encode_seconds_count ") < 2.0
        || metric(&text, "voxlight_frames_sent_total{format=\"jpeg\"}") < 2.0)
        && std::time::Instant::now() < deadline
    {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        text = scrape(app.clone()).await;
    }
    assert_eq!(metric(&text, "voxlight_sessions_active "), 1.0);
    assert!(metric(&text, "voxlight_frames_sent_total{format=\"jpeg\"}") >= 2.0);
    assert!(metric(&text, "voxlight_bytes_sent_total ") > 0.0);
    assert_eq!(
        metric(&text, "voxlight_errors_total{code=\"bad_message\"}"),
        1.0
    );
    assert!(metric(&text, "voxlight_gpu_seconds_total{technique=\"raymarch\"}") > 0.0);
    assert!(metric(&text, "voxlight_input_to_frame_seconds_count ") >= 1.0);
    assert!(metric(&text, "voxlight_encode_seconds_count ") >= 2.0);
    assert!(!text.contains("phantom"), "metrics must not name datasets");

    client.close().await;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    while metric(&scrape(app.clone()).await, "voxlight_viewers_active ") != 0.0 {
        assert!(
            std::time::Instant::now() < deadline,
            "the closed connection is still counted as a viewer"
        );
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    // The session itself waits out its reconnect grace period.
    assert_eq!(
        metric(&scrape(app.clone()).await, "voxlight_sessions_active "),
        1.0
    );
    server.stop().await.unwrap();
}
