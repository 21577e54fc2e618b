//! Shared sessions end to end: several viewers of one session, fan-out of one rendering,
//! backpressure from a stalled viewer, reconnecting into a session, the grace period, the
//! global GPU memory budget, and the load generator.

use std::time::{Duration, Instant};

use serde_json::json;
use voxlight_app::ServerConfig;
use voxlight_app::loadgen::LoadConfig;
use voxlight_protocol::{ClientMessage, ErrorCode, FrameFormat, ServerMessage};
use voxlight_tests::{Client, DecodedFrame, Incoming, TestServer};

fn session_id(welcome: &ServerMessage) -> String {
    match welcome {
        ServerMessage::Welcome { session, .. } => session.clone(),
        other => panic!("expected welcome, got {other:?}"),
    }
}

fn hello(size: u32, name: &str) -> serde_json::Value {
    json!({"type": "hello", "protocol": 1, "viewport": {"width": size, "height": size}, "name": name})
}

fn join(session: &str, name: &str) -> serde_json::Value {
    json!({"type": "hello", "protocol": 1, "session": session, "name": name})
}

/// `hello` asking for `technique`.
fn hello_with_technique(size: u32, name: &str, technique: &str) -> serde_json::Value {
    let mut hello = hello(size, name);
    hello["technique"] = technique.into();
    hello
}

/// Fails unless `reply` is an `error` of `code` whose text contains `says`.
fn assert_error(reply: ServerMessage, code: ErrorCode, says: &str) {
    match reply {
        ServerMessage::Error { code: got, message } => {
            assert_eq!(got, code, "{message}");
            assert!(message.contains(says), "{message}");
        }
        other => panic!("expected {code:?}, got {other:?}"),
    }
}

/// A TF visibly different from the sphere phantom's default.
fn red_tf() -> serde_json::Value {
    json!({"type": "tf", "points": [
        {"value": 0.0, "color": [1, 0.2, 0.1], "opacity": 0.0},
        {"value": 0.5, "color": [1, 0.2, 0.1], "opacity": 0.6},
        {"value": 1.0, "color": [1, 0.3, 0.1], "opacity": 0.9}
    ]})
}

/// The next edit `by_name` made, as another viewer learns it, and the version it produced.
async fn edit_by(client: &mut Client, by_name: &str) -> (ClientMessage, u64) {
    match client
        .text_where(|m| matches!(m, ServerMessage::Edited { by, .. } if by.name == by_name))
        .await
        .unwrap()
    {
        ServerMessage::Edited { edit, version, .. } => (*edit, version),
        _ => unreachable!(),
    }
}

/// Waits for the `edited` echo of the next edit `by_name` made and returns its version.
async fn edited_version(client: &mut Client, by_name: &str) -> u64 {
    edit_by(client, by_name).await.1
}

async fn converged_frame(client: &mut Client, version: u64) -> DecodedFrame {
    client
        .frame_where(|f| f.meta.converged && f.meta.scene_version >= version)
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_viewers_share_one_rendering_and_see_each_others_edits() {
    let server = TestServer::start(None).await.unwrap();
    let mut ada = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = ada.hello_with(hello(48, "Ada")).await.unwrap();
    let id = session_id(&welcome);
    ada.send_json(json!({"type": "quality", "iterations": 4}))
        .await
        .unwrap();
    // Bob joins after the edit is applied (else he may be welcomed at version 0).
    assert_eq!(edited_version(&mut ada, "Ada").await, 1);

    let mut bob = Client::connect(&server.ws_url()).await.unwrap();
    let joined = bob.hello_with(join(&id, "Bob")).await.unwrap();
    let ServerMessage::Welcome {
        session,
        joined: true,
        viewer,
        viewers,
        state,
        version,
        ..
    } = joined
    else {
        panic!("expected a joined welcome, got {joined:?}");
    };
    assert_eq!(session, id);
    assert_eq!(viewer.name, "Bob");
    assert_eq!(viewers.len(), 2);
    // The joiner gets the session's state, not its own hello's.
    assert_eq!((state.viewport.width, state.viewport.height), (48, 48));
    assert_eq!(version, 1, "Ada's iterations edit is version 1");
    let list = ada
        .text_where(|m| matches!(m, ServerMessage::Viewers { viewers } if viewers.len() == 2))
        .await
        .unwrap();
    assert!(matches!(list, ServerMessage::Viewers { .. }));

    // Bob edits; both are told, by name, with the version the edit produced.
    bob.send_json(red_tf()).await.unwrap();
    let version = edited_version(&mut ada, "Bob").await;
    assert_eq!(edited_version(&mut bob, "Bob").await, version);
    let a = converged_frame(&mut ada, version).await;
    let b = converged_frame(&mut bob, version).await;
    assert_eq!(a.meta.format, FrameFormat::Png);
    assert_eq!(
        (a.meta.seq, a.meta.iteration, a.meta.scene_version),
        (b.meta.seq, b.meta.iteration, b.meta.scene_version),
        "both viewers get the same frame of the same iteration"
    );
    assert_eq!(a.rgb, b.rgb);
    let red = a.rgb.chunks_exact(3).filter(|p| p[0] > p[2] + 40).count();
    assert!(
        red > 50,
        "Bob's red TF shows for Ada too ({red} red pixels)"
    );

    // One rendering for two viewers: each picture is encoded once per encoding, and sent to both.
    let text = server.metrics().await;
    let rendered = voxlight_tests::metric(&text, "voxlight_frames_rendered_total ");
    let encoded = voxlight_tests::metric(&text, "voxlight_frames_encoded_total ");
    let sent = voxlight_tests::metric(&text, "voxlight_frames_sent_total{format=\"jpeg\"}")
        + voxlight_tests::metric(&text, "voxlight_frames_sent_total{format=\"png\"}");
    assert!(
        encoded <= rendered,
        "encoded {encoded} > rendered {rendered}"
    );
    assert!(
        sent > encoded,
        "frames are fanned out: sent {sent}, encoded {encoded}"
    );

    // Ada edits the camera; Bob learns who did it and what.
    ada.send_json(json!({"type": "camera", "eye": [1.5, -1.8, 0.3], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30}))
        .await
        .unwrap();
    let (edit, _) = edit_by(&mut bob, "Ada").await;
    assert!(matches!(edit, ClientMessage::Camera(c) if c.eye == [1.5, -1.8, 0.3]));

    // Renaming reaches everyone through the viewer list.
    bob.send_json(json!({"type": "name", "name": "Robert"}))
        .await
        .unwrap();
    ada.text_where(|m| {
        matches!(m, ServerMessage::Viewers { viewers } if viewers.iter().any(|v| v.name == "Robert"))
    })
    .await
    .unwrap();
    ada.close().await;
    bob.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_viewer_holds_at_most_its_window_and_does_not_slow_the_others() {
    let server = TestServer::start(None).await.unwrap();
    // The stalled viewer acknowledges nothing and stops reading.
    let mut stalled = Client::connect(&server.ws_url()).await.unwrap();
    let mut hello = hello(96, "stalled");
    hello["max_in_flight"] = 2.into();
    let id = session_id(&stalled.hello_with(hello).await.unwrap());
    stalled
        .send_json(json!({"type": "quality", "iterations": 100000}))
        .await
        .unwrap();
    // A viewer that never reads at all and does not acknowledge either (TCP backpressure only).
    let mut deaf = Client::connect(&server.ws_url()).await.unwrap();
    deaf.send_json(join(&id, "deaf")).await.unwrap();

    let mut active = Client::connect(&server.ws_url()).await.unwrap();
    let mut join_active = join(&id, "active");
    join_active["max_in_flight"] = 2.into();
    active.hello_with(join_active).await.unwrap();
    let mut received = 0;
    let mut last_seq = 0;
    while received < 40 {
        match active.recv().await.unwrap() {
            Incoming::Frame(frame) => {
                assert!(frame.meta.seq > last_seq);
                last_seq = frame.meta.seq;
                received += 1;
                active
                    .send_json(json!({"type": "ack", "seq": frame.meta.seq}))
                    .await
                    .unwrap();
            }
            Incoming::Text(_) => {}
        }
        let in_flight = server.metric("voxlight_frames_in_flight ").await;
        assert!(
            in_flight <= 4.0,
            "two acknowledging viewers with a window of 2 each: {in_flight} in flight"
        );
    }
    // The stalled viewer got at most its window: two frames, then nothing until it acknowledges.
    let mut stalled_frames = Vec::new();
    let quiet = Instant::now() + Duration::from_secs(2);
    while Instant::now() < quiet {
        match tokio::time::timeout(Duration::from_millis(300), stalled.recv()).await {
            Ok(Ok(Incoming::Frame(frame))) => stalled_frames.push(frame.meta.seq),
            Ok(Ok(Incoming::Text(_))) => {}
            Ok(Err(e)) => panic!("{e}"),
            Err(_) => {}
        }
    }
    assert!(
        (1..=2).contains(&stalled_frames.len()),
        "window of 2, got {stalled_frames:?}"
    );
    // Once it acknowledges, it gets the newest frame, not the backlog.
    let last = *stalled_frames.last().unwrap();
    stalled
        .send_json(json!({"type": "ack", "seq": last}))
        .await
        .unwrap();
    let next = stalled.frame_where(|_| true).await.unwrap();
    assert!(
        next.meta.seq > last + 10,
        "after acknowledging {last} the stalled viewer should skip to the newest frame, got {}",
        next.meta.seq
    );
    // The frames this viewer skipped are counted by the time it holds the next one.
    let skipped = (next.meta.seq - last - 1) as f64;
    let counted = server.metric("voxlight_frames_skipped_total ").await;
    assert!(
        counted >= skipped,
        "the stalled viewer skipped {skipped} frames, the metric counts {counted}"
    );
    deaf.drop_connection();
    stalled.close().await;
    active.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_viewer_reconnects_into_the_same_converged_session() {
    let server = TestServer::start(None).await.unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let id = session_id(&client.hello_with(hello(40, "Ada")).await.unwrap());
    client
        .send_json(json!({"type": "quality", "iterations": 5}))
        .await
        .unwrap();
    client.send_json(red_tf()).await.unwrap();
    let version = edited_version(&mut client, "Ada").await;
    let before = converged_frame(&mut client, version).await;
    let rendered = server.metric("voxlight_frames_rendered_total ").await;
    client.drop_connection();

    let mut again = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = again.hello_with(join(&id, "Ada")).await.unwrap();
    let ServerMessage::Welcome {
        session,
        joined,
        state,
        ..
    } = welcome
    else {
        panic!("expected welcome, got {welcome:?}");
    };
    assert!(joined);
    assert_eq!(session, id);
    assert_eq!(state.iterations, 5);
    assert_eq!(state.tf.points.len(), 3, "the edited TF survived");
    // The converged picture comes at once, identical, and nothing was rendered again.
    let after = again.frame_where(|_| true).await.unwrap();
    assert!(after.meta.converged && after.meta.lossless);
    assert_eq!(after.meta.seq, before.meta.seq);
    assert_eq!(after.rgb, before.rgb);
    assert_eq!(
        server.metric("voxlight_frames_rendered_total ").await,
        rendered
    );
    again.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_expire_after_the_grace_period() {
    let server = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        grace_period: Some(Duration::from_millis(300)),
        ..Default::default()
    })
    .await
    .unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let id = session_id(&client.hello_with(hello(32, "Ada")).await.unwrap());
    client.close().await;
    let deadline = Instant::now() + Duration::from_secs(20);
    while server.metric("voxlight_sessions_expired_total ").await < 1.0 {
        assert!(Instant::now() < deadline, "the session never expired");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(server.metric("voxlight_sessions_active ").await, 0.0);
    let mut late = Client::connect(&server.ws_url()).await.unwrap();
    let reply = late.hello_with(join(&id, "late")).await.unwrap();
    assert_error(reply, ErrorCode::UnknownSession, "grace period");
    // A bad session id is the same error, and a new session still works.
    let mut fresh = Client::connect(&server.ws_url()).await.unwrap();
    let reply = fresh.hello_with(join("not-a-session", "x")).await.unwrap();
    assert_error(reply, ErrorCode::UnknownSession, "");
    let mut fresh = Client::connect(&server.ws_url()).await.unwrap();
    fresh.hello_with(hello(32, "fresh")).await.unwrap();
    fresh.frame_where(|_| true).await.unwrap();
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_global_gpu_memory_budget_refuses_what_does_not_fit() {
    // Room for the sphere phantom (128³ × 2 bytes) and a small session, not for a 512² one.
    let budget = 8 << 20;
    let server = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        gpu_memory_budget: Some(budget),
        ..Default::default()
    })
    .await
    .unwrap();
    let mut small = Client::connect(&server.ws_url()).await.unwrap();
    small.hello_with(hello(64, "small")).await.unwrap();
    small.frame_where(|_| true).await.unwrap();
    let in_use = server.metric("voxlight_gpu_memory_bytes ").await;
    assert!(in_use > 0.0 && in_use <= budget as f64, "{in_use}");

    let mut big = Client::connect(&server.ws_url()).await.unwrap();
    let reply = big.hello_with(hello(512, "big")).await.unwrap();
    assert_error(reply, ErrorCode::GpuMemory, "budget");
    // A technique whose own buffers do not fit (manylight's shadow maps) is refused after it
    // is built, by its actual size.
    let mut shadowed = Client::connect(&server.ws_url()).await.unwrap();
    let hello_manylight = hello_with_technique(64, "shadowed", "manylight");
    let reply = shadowed.hello_with(hello_manylight).await.unwrap();
    assert_error(reply, ErrorCode::GpuMemory, "budget");
    // Growing the viewport past the budget is refused too, and the session goes on.
    small
        .send_json(json!({"type": "viewport", "width": 600, "height": 600}))
        .await
        .unwrap();
    assert_error(small.recv_text().await.unwrap(), ErrorCode::GpuMemory, "");
    small
        .send_json(json!({"type": "camera", "eye": [0.5, -2.3, 0.4], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 30}))
        .await
        .unwrap();
    small
        .frame_where(|f| f.meta.scene_version >= 2 && f.width == 64)
        .await
        .unwrap();
    server.stop().await.unwrap();
}

/// A load of `n` sessions with `n` viewers each for `seconds` at size², 5 edits/s, a TF edit
/// every second, no background session.
fn load(url: String, n: u32, seconds: u64, size: u32) -> LoadConfig {
    LoadConfig {
        url,
        sessions: n,
        viewers: n,
        duration: Duration::from_secs(seconds),
        viewport: voxlight_protocol::Viewport {
            width: size,
            height: size,
        },
        dataset: None,
        technique: None,
        technique_options: None,
        token: None,
        edit_rate: 5.0,
        tf_interval: Duration::from_secs(1),
        background_sessions: 0,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loadgen_measures_latency_and_frame_rates() {
    let server = TestServer::start(None).await.unwrap();
    let report = voxlight_app::loadgen::run(LoadConfig {
        background_sessions: 1,
        ..load(server.ws_url(), 2, 4, 48)
    })
    .await
    .unwrap();
    assert_eq!(report.errors, 0, "{:?}", report.error_codes);
    assert_eq!(report.fps_per_viewer.count, 4);
    assert!(report.frames >= 8, "{report:?}");
    assert!(report.min_fps > 0.0, "{report:?}");
    assert!(report.input_to_frame_ms.count >= 2, "{report:?}");
    assert!(report.input_to_frame_ms.p50 > 0.0);
    assert!(report.bytes_per_s > 0.0);
    assert!(
        report.background_fps > 0.0,
        "the background session starved"
    );
    // Against a server that refuses it, errors are reported, not hidden.
    let refusing = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        access: voxlight_app::auth::Access {
            tokens: vec!["t".into()],
            allowed_origins: vec![],
        },
        ..Default::default()
    })
    .await
    .unwrap();
    let report = voxlight_app::loadgen::run(load(refusing.ws_url(), 1, 1, 32))
        .await
        .unwrap();
    assert_eq!(report.errors, 1, "{:?}", report.error_codes);
    refusing.stop().await.unwrap();
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn technique_details_reach_stats_and_frames() {
    let server = TestServer::start(None).await.unwrap();
    let (mut client, frame) = converged_session(&server, "manylight", 2).await;
    assert_eq!(frame.meta.technique, "manylight");
    let lights = frame.meta.details.virtual_lights.unwrap_or(0);
    assert!(lights > 0, "{:?}", frame.meta.details);
    assert!(frame.meta.details.shadow_map_bytes.unwrap_or(0) > 0);
    // Stats always follow the converged frame.
    let stats = client
        .text_where(|m| matches!(m, ServerMessage::Stats(s) if s.converged))
        .await
        .unwrap();
    let ServerMessage::Stats(stats) = stats else {
        unreachable!()
    };
    assert_eq!(stats.details.virtual_lights, Some(lights));
    client.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn irradiance_sessions_report_their_cache() {
    let server = TestServer::start(None).await.unwrap();
    let (client, frame) = converged_session(&server, "irradiance", 24).await;
    assert_eq!(frame.meta.technique, "irradiance");
    let details = &frame.meta.details;
    assert_eq!(details.cache_active, Some(true), "{details:?}");
    assert!(details.cache_entries.is_some(), "{details:?}");
    assert!(details.octree_references.is_some(), "{details:?}");
    let hit_rate = details.cache_hit_rate.unwrap_or(-1.0);
    assert!((0.0..=1.0).contains(&hit_rate), "{details:?}");
    assert!(
        frame.distinct_colors() > 8,
        "an irradiance picture of the phantom is not flat"
    );
    client.close().await;
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn technique_options_configure_the_session_and_reach_every_viewer() {
    let server = TestServer::start(None).await.unwrap();
    // Out-of-range options are refused before anything is built, naming the option.
    let mut refused = Client::connect(&server.ws_url()).await.unwrap();
    let mut bad = hello_with_technique(32, "Eve", "manylight");
    bad["technique_options"] = json!({"manylight": {"nodes": 40}});
    let reply = refused.hello_with(bad).await.unwrap();
    assert_error(reply, ErrorCode::BadValue, "manylight.nodes");
    refused.close().await;

    let mut ada = Client::connect(&server.ws_url()).await.unwrap();
    let mut start = hello_with_technique(32, "Ada", "manylight");
    // One set of lights (the face_res edit below keeps it), paths of at most 4 lights.
    start["technique_options"] = json!({"manylight": {"virtual_lights": 24, "face_res": 8,
        "max_bounces": 4, "iterations_per_set": 0}});
    let welcome = ada.hello_with(start).await.unwrap();
    let ServerMessage::Welcome { state, .. } = &welcome else {
        panic!("expected welcome, got {welcome:?}");
    };
    assert_eq!(state.technique_options.manylight.virtual_lights, Some(24));
    let frame = converged_after(&mut ada, 2).await;
    // Whole light paths are kept while they fit: at most the 24 asked for.
    let lights = frame.meta.details.virtual_lights.unwrap_or(0);
    assert!((12..=24).contains(&lights), "{:?}", frame.meta.details);
    // Slots for 24 + 24/4 lights, each a cube of 6 faces of 8² texels × 8 nodes × 4 bytes.
    let maps_8 = frame.meta.details.shadow_map_bytes.unwrap_or(0);
    assert_eq!(maps_8, 30 * 6 * 8 * 8 * 8 * 4);

    // A joiner sees the options in the state it is handed.
    let mut bob = Client::connect(&server.ws_url()).await.unwrap();
    let joined = bob
        .hello_with(join(&session_id(&welcome), "Bob"))
        .await
        .unwrap();
    let ServerMessage::Welcome { state, .. } = &joined else {
        panic!("expected welcome, got {joined:?}");
    };
    assert_eq!(state.technique_options.manylight.face_res, Some(8));

    // An edit changes only what it names, and every viewer learns it.
    ada.send_json(json!({"type": "technique", "name": "manylight",
        "options": {"manylight": {"face_res": 16}}}))
        .await
        .unwrap();
    let (edit, _) = edit_by(&mut bob, "Ada").await;
    let ClientMessage::Technique { name, options } = edit else {
        panic!("expected the technique edit, got {edit:?}");
    };
    assert_eq!(name, "manylight");
    assert_eq!(options.map(|o| o.manylight.face_res), Some(Some(16)));
    let frame = bob
        .frame_where(|f| f.meta.converged && f.meta.details.shadow_map_bytes != Some(maps_8))
        .await
        .unwrap();
    assert_eq!(frame.meta.details.virtual_lights, Some(lights), "kept");
    // Four times the texels per face: four times the shadow-map bytes.
    assert_eq!(frame.meta.details.shadow_map_bytes, Some(4 * maps_8));

    // A bad edit is refused and changes nothing; the session goes on.
    let (code, message) = refused_options(&mut ada, json!({"vsl_radius": 3.0})).await;
    assert_eq!(code, ErrorCode::BadValue);
    assert!(message.contains("manylight.vsl_radius"), "{message}");
    let (code, message) = refused_options(&mut ada, json!({"bogus": 1})).await;
    assert_eq!(code, ErrorCode::BadMessage);
    assert!(message.contains("bogus"), "{message}");
    ada.send_json(json!({"type": "technique", "name": "irradiance",
        "options": {"irradiance": {"locking": "screen", "priorities": false}}}))
        .await
        .unwrap();
    let frame = ada
        .frame_where(|f| f.meta.technique == "irradiance" && f.meta.converged)
        .await
        .unwrap();
    assert_eq!(frame.meta.details.cache_active, Some(true));
    ada.close().await;
    bob.close().await;
    server.stop().await.unwrap();
}

/// Sends manylight `options` that the server must refuse; returns the error's code and text.
async fn refused_options(client: &mut Client, options: serde_json::Value) -> (ErrorCode, String) {
    client
        .send_json(json!({"type": "technique", "name": "manylight",
            "options": {"manylight": options}}))
        .await
        .unwrap();
    match client
        .text_where(|m| matches!(m, ServerMessage::Error { .. }))
        .await
        .unwrap()
    {
        ServerMessage::Error { code, message } => (code, message),
        other => unreachable!("{other:?}"),
    }
}

/// A new 32² session of `technique`, converged after `iterations`: its viewer and that frame.
async fn converged_session(
    server: &TestServer,
    technique: &str,
    iterations: u32,
) -> (Client, DecodedFrame) {
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let hello = hello_with_technique(32, "Ada", technique);
    client.hello_with(hello).await.unwrap();
    let frame = converged_after(&mut client, iterations).await;
    (client, frame)
}

/// Asks for `iterations` and waits for the converged frame.
async fn converged_after(client: &mut Client, iterations: u32) -> DecodedFrame {
    client
        .send_json(json!({"type": "quality", "iterations": iterations}))
        .await
        .unwrap();
    client.frame_where(|f| f.meta.converged).await.unwrap()
}
