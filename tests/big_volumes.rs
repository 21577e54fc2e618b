//! A volume too large for the GPU is rendered from a downsampled copy, and the viewer is told
//! by how much and why (never a refusal without a way forward).

use std::time::Duration;

use serde_json::json;
use voxlight_app::ServerConfig;
use voxlight_protocol::ServerMessage;
use voxlight_tests::{Client, TestServer};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_volume_over_the_volume_budget_is_downsampled_and_the_viewer_told() {
    // The 128³ phantom takes 4 MiB as 16-bit texels; 1 MiB per volume allows half the edge.
    let server = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        max_volume_bytes: Some(1 << 20),
        ..Default::default()
    })
    .await
    .unwrap();
    let mut viewer = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = viewer
        .hello_with(
            json!({"type": "hello", "protocol": 1, "viewport": {"width": 32, "height": 32}}),
        )
        .await
        .unwrap();
    let ServerMessage::Welcome { dataset, .. } = welcome else {
        panic!("expected welcome, got {welcome:?}");
    };
    let details = dataset.details.expect("a loaded dataset has details");
    let reduced = details
        .downsampled
        .expect("the viewer is told it was downsampled");
    assert_eq!(reduced.factor, 2);
    assert_eq!(reduced.original_dims, [128, 128, 128]);
    assert!(reduced.reason.contains("MiB"), "{}", reduced.reason);
    assert_eq!(details.dims, [64, 64, 64]);
    assert!(
        details
            .warnings
            .iter()
            .any(|w| w.contains("downsampled 2×")),
        "{:?}",
        details.warnings
    );
    // The world box is unchanged (spacing doubled), and it renders.
    assert_eq!(details.world_extent, [1.0, 1.0, 1.0]);
    let frame = tokio::time::timeout(Duration::from_secs(60), viewer.frame_where(|_| true))
        .await
        .expect("a frame of the downsampled volume")
        .unwrap();
    assert!(frame.distinct_colors() > 1, "the picture shows the volume");
    viewer.close().await;
    server.stop().await.unwrap();
}
