//! The interaction mode end to end: while camera edits stream in, every technique shows reduced
//! previews (the scale falls to hold the frame target), at rest a full-resolution preview and
//! then the technique's lossless still (the scale rises again); the GI techniques keep their
//! view-independent state across the orbit (no photon retraced, no virtual light rebuilt, no
//! cache entry dropped).

use std::time::Duration;

use serde_json::json;
use voxlight_app::ServerConfig;
use voxlight_app::render_service::Interaction;
use voxlight_protocol::{ServerMessage, TechniqueDetails};
use voxlight_tests::{Client, DecodedFrame, Incoming, TestServer};

const CAMERA_EDITS: u64 = 5;

/// The frames from the first of `CAMERA_EDITS` orbit steps until the converged still that shows
/// the last one.
async fn orbit(client: &mut Client) -> Vec<DecodedFrame> {
    for k in 1..=CAMERA_EDITS {
        let a = (k as f32 * 4.0).to_radians();
        client
            .send_json(
                json!({"type": "camera", "eye": [2.4 * a.sin(), -2.4 * a.cos(), 0.3],
                "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 35}),
            )
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(40)).await;
    }
    let mut echoes = 0;
    let mut last_version = u64::MAX;
    let mut frames = Vec::new();
    loop {
        match client.recv().await.unwrap() {
            Incoming::Text(message) => match *message {
                ServerMessage::Edited { version, .. } => {
                    echoes += 1;
                    if echoes == CAMERA_EDITS {
                        last_version = version;
                    }
                }
                ServerMessage::Error { code, message } => panic!("{code:?}: {message}"),
                _ => {}
            },
            Incoming::Frame(frame) => {
                let done = frame.meta.converged && frame.meta.scene_version >= last_version;
                frames.push(frame);
                if done {
                    return frames;
                }
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_orbit_shows_reduced_previews_then_the_still_and_keeps_the_gi_state() {
    let server = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        preload: false,
        // A 1 ms target: every preview is too slow, so the scale falls to its floor.
        interaction: Some(Interaction {
            enabled: true,
            frame_target: Duration::from_millis(1),
            rest_after: Duration::from_millis(400),
        }),
        ..Default::default()
    })
    .await
    .unwrap();
    for technique in ["raymarch", "photon", "manylight", "irradiance"] {
        let mut client = Client::connect(&server.ws_url()).await.unwrap();
        // manylight with one set of virtual lights: the orbit must not rebuild it (with a new
        // set per iteration, the default, iterations past the first trace sets whatever the
        // camera does; gpu_manylight checks that a camera move alone traces none).
        let welcome = client
            .hello_with(
                json!({"type": "hello", "protocol": 1, "technique": technique,
                "viewport": {"width": 48, "height": 48},
                "technique_options": {"manylight": {"iterations_per_set": 0}}}),
            )
            .await
            .unwrap();
        assert!(
            matches!(welcome, ServerMessage::Welcome { .. }),
            "{welcome:?}"
        );
        // Enough iterations for the irradiance cache to hold entries.
        let iterations = if technique == "irradiance" { 64 } else { 3 };
        client
            .send_json(json!({"type": "quality", "iterations": iterations}))
            .await
            .unwrap();
        let before = client
            .frame_where(|f| f.meta.converged)
            .await
            .unwrap()
            .meta
            .details;
        let frames = orbit(&mut client).await;

        let previews: Vec<&DecodedFrame> = frames.iter().filter(|f| f.meta.preview).collect();
        assert!(!previews.is_empty(), "{technique}: no preview while moving");
        for p in &previews {
            assert!(
                !p.meta.lossless && !p.meta.converged,
                "{technique}: a preview is lossy"
            );
            let expected = (48.0 * p.meta.resolution_scale).ceil() as u32;
            assert_eq!((p.width, p.height), (expected, expected), "{technique}");
        }
        let last_reduced = frames
            .iter()
            .rposition(|f| f.meta.preview && f.meta.resolution_scale < 1.0)
            .unwrap_or_else(|| panic!("{technique}: the scale never fell"));
        assert!(
            frames[last_reduced + 1..]
                .iter()
                .any(|f| f.meta.preview && f.meta.resolution_scale == 1.0),
            "{technique}: no full-resolution preview at rest"
        );
        let still = frames.last().unwrap();
        assert!(still.meta.lossless && !still.meta.preview, "{technique}");
        assert_eq!(
            (still.width, still.height, still.meta.resolution_scale),
            (48, 48, 1.0)
        );

        let after = &still.meta.details;
        check_state_kept(technique, &before, after);
        client.close().await;
    }
    server.stop().await.unwrap();
}

fn check_state_kept(technique: &str, before: &TechniqueDetails, after: &TechniqueDetails) {
    match technique {
        "photon" => {
            assert!(before.photons_traced.unwrap_or(0) > 0, "{before:?}");
            assert_eq!(
                after.photons_traced, before.photons_traced,
                "the orbit retraced photons"
            );
        }
        "manylight" => {
            assert!(before.virtual_lights.unwrap_or(0) > 0, "{before:?}");
            assert_eq!(after.virtual_lights, before.virtual_lights);
            // The build time is that of the last build: the same value, no new build.
            assert_eq!(
                after.build_ms, before.build_ms,
                "the orbit rebuilt virtual lights"
            );
        }
        "irradiance" => {
            let entries = before.cache_entries.unwrap_or(0);
            assert!(entries > 0, "{before:?}");
            assert!(
                after.cache_entries.unwrap_or(0) >= entries,
                "the orbit dropped cache entries: {before:?} -> {after:?}"
            );
        }
        _ => {}
    }
}
