//! End to end: the real server on a free port, a scripted WebSocket client, real frames.

use axum::body::Body;
use axum::http::{Request, StatusCode};
use http_body_util::BodyExt;
use serde_json::json;
use tower::ServiceExt;
use voxlight_protocol::{ErrorCode, FrameFormat, ServerMessage};
use voxlight_tests::{Client, DecodedFrame, Incoming, TestServer, metric, shared_data};

fn assert_error(message: &ServerMessage, expected: ErrorCode) {
    match message {
        ServerMessage::Error { code, message } => {
            assert_eq!(*code, expected, "error message: {message}");
            assert!(!message.is_empty());
        }
        other => panic!("expected an {expected:?} error, got {other:?}"),
    }
}

/// A camera edit from `eye` toward the origin, z up, 30° field of view.
fn camera(eye: [f64; 3]) -> serde_json::Value {
    json!({"type": "camera", "eye": eye, "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30})
}

/// Sends `edit` and waits for a frame of scene version `version` or later.
async fn edit_and_frame(
    client: &mut Client,
    edit: serde_json::Value,
    version: u64,
) -> DecodedFrame {
    client.send_json(edit).await.unwrap();
    client
        .frame_where(|f| f.meta.scene_version >= version)
        .await
        .unwrap()
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
    let tf = json!({"type": "tf", "points": [
        {"value": 0.0, "color": [0.1, 0.2, 0.9], "opacity": 0.0},
        {"value": 1.0, "color": [0.1, 0.2, 0.9], "opacity": 0.3}
    ]});
    let edited = edit_and_frame(&mut client, tf, 1).await;
    assert!(
        edited.max_diff(&reference) > 40,
        "TF edit did not change the picture"
    );

    // Garbage: an error reply each, then frames still come for the next edit.
    client.send_text("this is not json".into()).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    let answers = [
        (json!({"type": "warp_drive"}), ErrorCode::BadMessage),
        (
            json!({"type": "viewport", "width": 0, "height": 10}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "tf", "points": [{"value": 2.0, "color": [1, 1, 1], "opacity": 1}]}),
            ErrorCode::BadValue,
        ),
    ];
    for (message, code) in answers {
        refused(&mut client, message.to_string(), code).await;
    }
    client.send_binary(vec![1, 2, 3]).await.unwrap();
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::BadMessage);
    let too_large = "x".repeat(voxlight_protocol::MAX_MESSAGE_BYTES + 1);
    refused(&mut client, too_large, ErrorCode::TooLarge).await;
    let answers = [
        (
            json!({"type": "technique", "name": "nope"}),
            ErrorCode::UnknownTechnique,
        ),
        (
            json!({"type": "dataset", "name": "nope"}),
            ErrorCode::UnknownDataset,
        ),
        (json!({"type": "hello", "protocol": 1}), ErrorCode::NotReady),
    ];
    for (message, code) in answers {
        refused(&mut client, message.to_string(), code).await;
    }
    // A viewport the protocol allows but this GPU cannot hold is refused before allocation
    // (lavapipe binds at most 128 MiB per storage buffer: 8 Mi pixels of HDR accumulation).
    let max_pixels = server.state.max_viewport_pixels;
    assert!(
        max_pixels >= 1024 * 1024,
        "a 1024² viewport must fit: {max_pixels}"
    );
    if 4096 * 4096 > max_pixels {
        let huge = json!({"type": "viewport", "width": 4096, "height": 4096});
        refused(&mut client, huge.to_string(), ErrorCode::GpuMemory).await;
    }

    let mut turn = camera([2.0, -1.0, 0.5]);
    turn["fov_deg"] = 35.into();
    let after = edit_and_frame(&mut client, turn, 2).await;
    assert_eq!((after.width, after.height), (96, 64));
    assert!(
        after.max_diff(&edited) > 20,
        "camera edit did not change the picture"
    );

    // A new viewport: frames follow it.
    let viewport = json!({"type": "viewport", "width": 64, "height": 80});
    let resized = edit_and_frame(&mut client, viewport, 3).await;
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
    let early = json!({"type": "camera", "eye": [0, 0, 2], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 30});
    refused(&mut client, early.to_string(), ErrorCode::NotReady).await;
    refused(&mut client, "{".into(), ErrorCode::BadMessage).await;
    // Still usable: a proper hello works.
    client.hello(None, 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    client.close().await;

    let bad_hellos = [
        (
            json!({"type": "hello", "protocol": 99}),
            ErrorCode::ProtocolVersion,
        ),
        (
            json!({"type": "hello", "protocol": 1, "dataset": "../../etc/passwd"}),
            ErrorCode::UnknownDataset,
        ),
    ];
    for (hello, code) in bad_hellos {
        let mut client = Client::connect(&server.ws_url()).await.unwrap();
        refused(&mut client, hello.to_string(), code).await;
    }
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
    let server = TestServer::start_with(voxlight_app::ServerConfig {
        data_dir: Some(shared_data()),
        default_dataset: None,
        preload: true,
        ..Default::default()
    })
    .await
    .unwrap();
    let app = voxlight_app::app(server.state.clone());
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
    let server = TestServer::start_with(voxlight_app::ServerConfig {
        data_dir: None,
        default_dataset: Some("phantom:sphere".into()),
        preload: false,
        access: voxlight_app::auth::Access {
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
    let app = voxlight_app::app(server.state.clone());
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
    let burst = 3 * voxlight_protocol::MAX_MESSAGES_PER_SECOND;
    for _ in 0..burst {
        client.send_json(camera([0.3, -2.4, 0.1])).await.unwrap();
    }
    assert_error(&client.recv_text().await.unwrap(), ErrorCode::RateLimited);
    // After a pause the session takes edits again and renders them.
    tokio::time::sleep(std::time::Duration::from_secs(2)).await;
    let accepted = 2 * voxlight_protocol::MAX_MESSAGES_PER_SECOND as u64;
    let frame = edit_and_frame(&mut client, camera([2.4, 0.0, 0.2]), accepted + 1).await;
    assert_eq!((frame.width, frame.height), (32, 32));
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_count_sessions_frames_errors_and_latency() {
    let server = TestServer::start(None).await.unwrap();
    let app = voxlight_app::app(server.state.clone());
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
    refused(&mut client, "garbage".into(), ErrorCode::BadMessage).await;
    edit_and_frame(&mut client, camera([0.5, -2.3, 0.4]), 1).await;

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

/// Sends one message and expects an `error` with `code`; returns its text.
async fn refused(client: &mut Client, message: String, code: ErrorCode) -> String {
    client.send_text(message.clone()).await.unwrap();
    match client.recv_text().await.unwrap() {
        ServerMessage::Error {
            code: got,
            message: text,
        } => {
            assert_eq!(
                got, code,
                "{message:.200} was answered with {got:?}: {text}"
            );
            assert!(!text.is_empty());
            text
        }
        other => panic!("{message:.200} was answered with {other:?}, expected a {code:?} error"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_hostile_message_gets_an_error_and_the_session_goes_on() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(None, 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    let camera_text = |eye: &str, fov: &str| {
        format!(r#"{{"type":"camera","eye":{eye},"target":[0,0,0],"up":[0,0,1],"fov_deg":{fov}}}"#)
    };
    let nested = |depth: usize| "[".repeat(depth) + &"]".repeat(depth);
    let bad_message = [
        // Not JSON, not an object, no or an unknown type.
        "".to_owned(),
        "null".into(),
        "42".into(),
        r#""hello""#.into(),
        "[]".into(),
        "{}".into(),
        r#"{"type":5}"#.into(),
        r#"{"type":"warp_drive"}"#.into(),
        r#"{"type":"TF","points":[]}"#.into(),
        "\u{feff}{\"type\":\"ack\",\"seq\":1}".into(),
        r#"{"type":"ack","seq":1}{"type":"ack","seq":2}"#.into(),
        // Numbers JSON does not have, or that fit no field.
        r#"{"type":"params","exposure":NaN}"#.into(),
        r#"{"type":"params","exposure":Infinity}"#.into(),
        r#"{"type":"params","exposure":-Infinity}"#.into(),
        r#"{"type":"params","exposure":"Infinity"}"#.into(),
        r#"{"type":"params","exposure":1e400}"#.into(),
        camera_text("[0,-2,1e999]", "30"),
        // Wrong JSON types and missing fields.
        camera_text(r#""here""#, "30"),
        camera_text("[0,-2]", "30"),
        camera_text("[0,-2,0,5]", "30"),
        camera_text("[0,-2,null]", "30"),
        r#"{"type":"camera","eye":[0,-2,0]}"#.into(),
        r#"{"type":"viewport","width":"64","height":64}"#.into(),
        r#"{"type":"viewport","width":64.5,"height":64}"#.into(),
        r#"{"type":"viewport","width":-64,"height":64}"#.into(),
        r#"{"type":"viewport","width":4294967296,"height":64}"#.into(),
        r#"{"type":"tf","points":{}}"#.into(),
        r#"{"type":"tf","points":[{"value":0.5}]}"#.into(),
        r#"{"type":"tf"}"#.into(),
        r#"{"type":"lights","lights":[{"kind":"laser","power":1}]}"#.into(),
        r#"{"type":"ack","seq":-1}"#.into(),
        r#"{"type":"ack","seq":18446744073709551616}"#.into(),
        r#"{"type":"name","name":7}"#.into(),
        r#"{"type":"dataset","name":null}"#.into(),
        r#"{"type":"technique","name":"raymarch","options":{"photon":{"lock":"x"}}}"#.into(),
        r#"{"type":"technique","name":"raymarch","options":{"photon":{"passes":"many"}}}"#.into(),
        // quality: values that are no u8 / u32.
        r#"{"type":"quality","jpeg_quality":300}"#.into(),
        r#"{"type":"quality","jpeg_quality":256}"#.into(),
        r#"{"type":"quality","jpeg_quality":-1}"#.into(),
        r#"{"type":"quality","jpeg_quality":50.5}"#.into(),
        r#"{"type":"quality","jpeg_quality":"high"}"#.into(),
        r#"{"type":"quality","iterations":-1}"#.into(),
        r#"{"type":"quality","iterations":4294967296}"#.into(),
        r#"{"type":"quality","iterations":1e20}"#.into(),
        // Deep nesting, in a field and at the top (serde_json stops at 128 levels).
        format!(r#"{{"type":"tf","points":{}}}"#, nested(20_000)),
        nested(30_000),
        format!(r#"{{"type":"name","name":"x","extra":{}}}"#, nested(200)),
        "{\"a\":".repeat(10_000),
    ];
    for message in bad_message {
        assert!(message.len() <= voxlight_protocol::MAX_MESSAGE_BYTES);
        refused(&mut client, message, ErrorCode::BadMessage).await;
    }
    let too_many_points: Vec<_> = (0..=voxlight_protocol::MAX_TF_POINTS)
        .map(|i| json!({"value": i as f32 / 300.0, "color": [1, 1, 1], "opacity": 0.5}))
        .collect();
    let too_many_lights: Vec<_> = (0..=voxlight_protocol::MAX_LIGHTS)
        .map(|_| json!({"kind": "environment", "radiance": [0.1, 0.1, 0.1]}))
        .collect();
    let bad_value = [
        // Out of range quality.
        json!({"type": "quality", "jpeg_quality": 0}),
        json!({"type": "quality", "jpeg_quality": 101}),
        json!({"type": "quality", "iterations": 0}),
        json!({"type": "quality", "iterations": 65537}),
        json!({"type": "quality", "iterations": u32::MAX}),
        // A valid quality beside a bad one: refused as a whole.
        json!({"type": "quality", "jpeg_quality": 50, "iterations": 0}),
        // Finite JSON numbers beyond f32 (they become ±inf) and other non-finite results.
        json!({"type": "params", "exposure": 1e39}),
        json!({"type": "params", "density_scale": -1e39}),
        json!({"type": "params", "g": 1e39}),
        json!({"type": "params", "g": 0.99}),
        json!({"type": "params", "exposure": 0}),
        json!({"type": "params", "density_scale": -1}),
        json!({"type": "camera", "eye": [1e39, 0, 0], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30}),
        json!({"type": "camera", "eye": [3e38, 0, 0], "target": [-3e38, 0, 0], "up": [0, 0, 1], "fov_deg": 30}),
        json!({"type": "camera", "eye": [0, -2, 0], "target": [0, -2, 0], "up": [0, 0, 1], "fov_deg": 30}),
        json!({"type": "camera", "eye": [0, -2, 0], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 30}),
        json!({"type": "camera", "eye": [0, -2, 0], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 0}),
        json!({"type": "camera", "eye": [0, -2, 0], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 1e39}),
        json!({"type": "camera", "eye": [1e-30, 0, 0], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30}),
        json!({"type": "tf", "points": [{"value": 0.5, "color": [1, 1, 1], "opacity": 1e39}]}),
        json!({"type": "tf", "points": [{"value": -1e39, "color": [1, 1, 1], "opacity": 0.5}]}),
        json!({"type": "tf", "points": [{"value": 0.5, "color": [1, -0.1, 1], "opacity": 0.5}]}),
        json!({"type": "tf", "points": too_many_points}),
        json!({"type": "lights", "lights": too_many_lights}),
        json!({"type": "lights", "lights": [{"kind": "directional", "direction": [0, 0, 0], "irradiance": [1, 1, 1]}]}),
        json!({"type": "lights", "lights": [{"kind": "directional", "direction": [1e39, 0, 0], "irradiance": [1, 1, 1]}]}),
        json!({"type": "lights", "lights": [{"kind": "point", "position": [0, 0, 2], "intensity": [1e39, 1, 1]}]}),
        json!({"type": "lights", "lights": [{"kind": "environment", "radiance": [-1, 0, 0]}]}),
        // Viewports the protocol does not allow.
        json!({"type": "viewport", "width": 0, "height": 0}),
        json!({"type": "viewport", "width": 4097, "height": 32}),
        json!({"type": "viewport", "width": u32::MAX, "height": u32::MAX}),
        // Technique options out of range.
        json!({"type": "technique", "name": "raymarch", "options": {"photon": {"passes": 0}}}),
        json!({"type": "technique", "name": "raymarch", "options": {"manylight": {"virtual_lights": 1_000_000}}}),
        json!({"type": "technique", "name": "raymarch", "options": {"irradiance": {"gamma": 1e39}}}),
    ];
    for message in bad_value {
        refused(&mut client, message.to_string(), ErrorCode::BadValue).await;
    }
    // A message between the protocol limit and the transport limit: too_large, and nothing
    // else happens.
    for len in [
        voxlight_protocol::MAX_MESSAGE_BYTES + 1,
        super_large_but_accepted_by_the_transport(),
    ] {
        let padded = format!(r#"{{"type":"name","name":"{}"}}"#, "x".repeat(len));
        refused(&mut client, padded, ErrorCode::TooLarge).await;
    }
    // A hello on a live connection.
    refused(
        &mut client,
        json!({"type": "hello", "protocol": 1, "viewport": {"width": 0, "height": 0}}).to_string(),
        ErrorCode::NotReady,
    )
    .await;

    // None of it changed the session: the next edit is version 1, and it renders.
    client.send_json(camera([2.4, 0.0, 0.2])).await.unwrap();
    let edited = client
        .text_where(|m| matches!(m, ServerMessage::Edited { .. }))
        .await
        .unwrap();
    assert!(
        matches!(edited, ServerMessage::Edited { version: 1, .. }),
        "a refused message changed the scene version: {edited:?}"
    );
    let frame = client
        .frame_where(|f| f.meta.scene_version >= 1)
        .await
        .unwrap();
    assert_eq!((frame.width, frame.height), (32, 32));
    server.stop().await.unwrap();
}

/// Just under the transport limit (1 MiB), minus room for the JSON around it.
fn super_large_but_accepted_by_the_transport() -> usize {
    (1 << 20) - 64
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_empty_tf_is_refused_and_one_transparent_point_shows_the_environment() {
    // Issue 22: an empty TF is malformed (`bad_value`, nothing changes); one point of opacity
    // 0 is how a client makes the volume transparent, and renders the environment alone.
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = client.hello(None, 32, 32).await.unwrap();
    let ServerMessage::Welcome { techniques, .. } = welcome else {
        unreachable!()
    };
    client
        .send_json(json!({"type": "lights", "lights": [{"kind": "environment", "radiance": [0.25, 0.5, 0.75]}]}))
        .await
        .unwrap();
    client
        .send_json(json!({"type": "tf", "points": []}))
        .await
        .unwrap();
    let refused = client
        .text_where(|m| matches!(m, ServerMessage::Error { .. }))
        .await
        .unwrap();
    assert_error(&refused, ErrorCode::BadValue);
    client
        .send_json(json!({"type": "tf", "points": [{"value": 0.5, "color": [1.0, 1.0, 1.0], "opacity": 0.0}]}))
        .await
        .unwrap();
    let echoed = client
        .text_where(|m| {
            matches!(m, ServerMessage::Edited { edit, .. }
                if matches!(**edit, voxlight_protocol::ClientMessage::Tf(ref tf) if tf.points.len() == 1))
        })
        .await
        .unwrap();
    let ServerMessage::Edited { version, .. } = echoed else {
        unreachable!()
    };
    let frame = client
        .frame_where(|f| f.meta.scene_version >= version)
        .await
        .unwrap();
    assert_eq!(
        frame.distinct_colors(),
        1,
        "a transparent TF shows the environment only"
    );
    // Every technique takes it (nothing to scatter from, no lights inside): converged
    // pictures of the environment, no error.
    client
        .send_json(json!({"type": "quality", "iterations": 2}))
        .await
        .unwrap();
    // The quality edit is `version + 1`; each technique switch one more.
    let others = techniques.iter().filter(|t| t.name != "raymarch");
    for (version, technique) in (version + 2..).zip(others) {
        client
            .send_json(json!({"type": "technique", "name": technique.name}))
            .await
            .unwrap();
        let still = client
            .frame_where(|f| f.meta.scene_version >= version && f.meta.converged)
            .await
            .unwrap_or_else(|e| panic!("{}: {e}", technique.name));
        assert_eq!(still.meta.technique, technique.name);
        assert_eq!(still.distinct_colors(), 1, "{}", technique.name);
    }
    server.stop().await.unwrap();
}

type RawSocket =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// Reads until the server closes; the close frame's code and reason (None: the connection
/// ended without one).
async fn close_frame(ws: &mut RawSocket) -> Option<(u16, String)> {
    use futures_util::StreamExt;
    use tokio_tungstenite::tungstenite::Message;
    loop {
        let next = tokio::time::timeout(std::time::Duration::from_secs(30), ws.next())
            .await
            .expect("the server neither closed nor answered within 30 s");
        match next {
            Some(Ok(Message::Close(frame))) => {
                return frame.map(|f| (u16::from(f.code), f.reason.to_string()));
            }
            Some(Ok(_)) => continue,
            Some(Err(_)) | None => return None,
        }
    }
}

async fn raw_connect(server: &TestServer) -> RawSocket {
    tokio_tungstenite::connect_async(server.ws_url())
        .await
        .unwrap()
        .0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_over_the_transport_limit_closes_with_1009() {
    use futures_util::SinkExt;
    use tokio_tungstenite::tungstenite::Message;
    use tokio_tungstenite::tungstenite::protocol::frame::Frame;
    use tokio_tungstenite::tungstenite::protocol::frame::coding::{Data, OpCode};
    let server = TestServer::start(None).await.unwrap();
    let over = (1 << 20) + 1;
    let hello = json!({"type": "hello", "protocol": 1, "viewport": {"width": 32, "height": 32}});

    // Before hello, and after it (text and binary): the client hears 1009, not silence.
    for (after_hello, message) in [
        (false, Message::Text("x".repeat(over).into())),
        (true, Message::Text("x".repeat(over).into())),
        (true, Message::Binary(vec![7u8; 4 << 20].into())),
    ] {
        let mut ws = raw_connect(&server).await;
        if after_hello {
            ws.send(Message::Text(hello.to_string().into()))
                .await
                .unwrap();
        }
        // The server may close before it has read everything: a failed send is fine.
        let _ = ws.send(message).await;
        let (code, reason) = close_frame(&mut ws)
            .await
            .expect("the server must close with a close frame, not drop the connection");
        assert_eq!(code, 1009, "close reason: {reason}");
        assert!(reason.contains("limit"), "{reason}");
    }

    // Text that is not UTF-8: 1007.
    let mut ws = raw_connect(&server).await;
    ws.send(Message::Text(hello.to_string().into()))
        .await
        .unwrap();
    let frame = Frame::message(vec![b'{', 0xff, 0xfe, b'}'], OpCode::Data(Data::Text), true);
    let _ = ws.send(Message::Frame(frame)).await;
    let (code, _) = close_frame(&mut ws).await.expect("a close frame");
    assert_eq!(code, 1007);

    // A frame with reserved bits set (no extension was negotiated): 1002.
    let mut ws = raw_connect(&server).await;
    ws.send(Message::Text(hello.to_string().into()))
        .await
        .unwrap();
    let mut frame = Frame::message(b"{}".to_vec(), OpCode::Data(Data::Text), true);
    frame.header_mut().rsv1 = true;
    let _ = ws.send(Message::Frame(frame)).await;
    let (code, _) = close_frame(&mut ws).await.expect("a close frame");
    assert_eq!(code, 1002);

    // The server is unharmed: the sessions it had are gone with their viewers, a new one works.
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(None, 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hellos_with_absurd_values_are_refused() {
    let server = TestServer::start(None).await.unwrap();
    let cases = [
        (
            json!({"type": "hello", "protocol": 1, "viewport": {"width": 0, "height": 0}}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "hello", "protocol": 1, "viewport": {"width": 100_000, "height": 100_000}}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "hello", "protocol": 1, "viewport": {"width": u32::MAX, "height": 1}}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "hello", "protocol": 1, "max_in_flight": 0}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "hello", "protocol": 1, "max_in_flight": 9}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "hello", "protocol": 1, "technique_options": {"photon": {"bounces": 0}}}),
            ErrorCode::BadValue,
        ),
        (
            json!({"type": "hello", "protocol": 1, "technique": "x".repeat(10_000)}),
            ErrorCode::UnknownTechnique,
        ),
        (
            json!({"type": "hello", "protocol": 1, "session": "0".repeat(60_000)}),
            ErrorCode::UnknownSession,
        ),
        (
            json!({"type": "hello", "protocol": 1, "dataset": "\u{0}/../../etc/passwd"}),
            ErrorCode::UnknownDataset,
        ),
        (
            json!({"type": "hello", "protocol": u32::MAX}),
            ErrorCode::ProtocolVersion,
        ),
    ];
    for (hello, code) in cases {
        let mut client = Client::connect(&server.ws_url()).await.unwrap();
        let reply = client.hello_with(hello.clone()).await.unwrap();
        match reply {
            ServerMessage::Error { code: got, .. } => assert_eq!(got, code, "{hello:.200}"),
            other => panic!("{hello:.200} was answered with {other:?}"),
        }
    }
    // Values that do not parse leave the connection waiting for a proper hello.
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    for hello in [
        r#"{"type":"hello","protocol":1,"viewport":{"width":4294967296,"height":1}}"#,
        r#"{"type":"hello","protocol":-1}"#,
        r#"{"type":"hello","protocol":1,"viewport":{"width":1e400,"height":1}}"#,
        r#"{"type":"hello"}"#,
    ] {
        refused(&mut client, hello.to_owned(), ErrorCode::BadMessage).await;
    }
    // A display name of any length and content is cut to 64 characters.
    let long_name = "\u{202e}\u{0}é".repeat(2_000);
    let welcome = client
        .hello_with(json!({"type": "hello", "protocol": 1, "name": long_name, "viewport": {"width": 32, "height": 32}}))
        .await
        .unwrap();
    let ServerMessage::Welcome { viewer, .. } = welcome else {
        panic!("expected welcome, got {welcome:?}")
    };
    assert!(viewer.name.chars().count() <= voxlight_protocol::MAX_NAME_CHARS);
    client.frame_where(|_| true).await.unwrap();
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_dataset_fails_to_load_and_the_viewer_picks_another() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: &[u8]| std::fs::write(dir.path().join(name), bytes).unwrap();
    // Truncated data, a header that lies about its size, garbage under a volume name, a VTK
    // file cut in its header, and one good volume.
    write(
        "truncated.nrrd",
        b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 64 64 64\nencoding: raw\n\n0123456789",
    );
    write(
        "huge.nrrd",
        b"NRRD0004\ntype: double\ndimension: 3\nsizes: 4000000000 4000000000 4000000000\nencoding: gzip\n\n",
    );
    write("garbage.nii", &[0x5a; 400]);
    write(
        "cut.vti",
        b"<?xml version=\"1.0\"?>\n<VTKFile type=\"ImageData\" version=\"1.0\"><ImageData WholeExtent=\"0 7 0",
    );
    let mut good = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 8 8 8\nencoding: raw\n\n".to_vec();
    good.extend((0..512u32).map(|i| ((i * 37) % 251) as u8));
    write("good.nrrd", &good);
    let server = TestServer::start(Some(dir.path().to_owned()))
        .await
        .unwrap();
    let folder = dir.path().display().to_string();

    // A hello naming a corrupt dataset is refused (and the socket closed, as documented);
    // the next connection opens a good one.
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let reply = client
        .hello_with(json!({"type": "hello", "protocol": 1, "dataset": "truncated.nrrd"}))
        .await
        .unwrap();
    assert!(
        matches!(&reply, ServerMessage::Error { code: ErrorCode::LoadFailed, message } if message.contains("truncated")),
        "{reply:?}"
    );

    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    client.hello(Some("phantom:sphere"), 32, 32).await.unwrap();
    client.frame_where(|_| true).await.unwrap();
    for name in ["truncated.nrrd", "huge.nrrd", "garbage.nii", "cut.vti"] {
        let text = refused(
            &mut client,
            json!({"type": "dataset", "name": name}).to_string(),
            ErrorCode::LoadFailed,
        )
        .await;
        assert!(text.contains(name), "{text}");
        assert!(
            !text.contains(&folder),
            "server folders must not reach clients: {text}"
        );
    }
    // Still the sphere, still rendering: an edit gives a frame.
    edit_and_frame(&mut client, camera([2.4, 0.0, 0.2]), 1).await;
    // Another dataset loads.
    client
        .send_json(json!({"type": "dataset", "name": "good.nrrd"}))
        .await
        .unwrap();
    let loaded = client
        .text_where(|m| matches!(m, ServerMessage::DatasetLoaded { .. }))
        .await
        .unwrap();
    let ServerMessage::DatasetLoaded { dataset, state, .. } = loaded else {
        unreachable!()
    };
    assert_eq!(dataset.name, "good.nrrd");
    assert_eq!(dataset.details.unwrap().dims, [8, 8, 8]);
    assert_eq!(state.dataset, "good.nrrd");
    client
        .frame_where(|f| f.meta.scene_version >= 2)
        .await
        .unwrap();
    server.stop().await.unwrap();
}
