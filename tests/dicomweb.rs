//! A PACS over DICOMweb, for real: Orthanc (Debian `orthanc` + `orthanc-dicomweb`) on loopback
//! with a password, filled with the shared chest CT; the server lists its series (QIDO-RS),
//! a viewer opens one, sees its instances arrive (`loading`), and the fetched volume equals the
//! local series voxel for voxel.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::json;
use voxlight_app::{DicomWebSource, ServerConfig};
use voxlight_protocol::ServerMessage;
use voxlight_tests::{Client, Incoming, TestServer, shared_data};

const ORTHANC: &str = "/usr/sbin/Orthanc";
const DICOMWEB_PLUGIN: &str = "/usr/share/orthanc/plugins/libOrthancDicomWeb.so";
const USER: &str = "radiology";
const PASSWORD: &str = "s3cret-for-tests";

/// Orthanc on a free loopback port with its own storage; killed on drop.
struct Orthanc {
    child: Child,
    port: u16,
    _storage: tempfile::TempDir,
}

impl Drop for Orthanc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .timeout_global(Some(Duration::from_secs(60)))
        .http_status_as_error(false)
        .build()
        .into()
}

fn basic() -> String {
    use base64::Engine as _;
    format!(
        "Basic {}",
        base64::engine::general_purpose::STANDARD.encode(format!("{USER}:{PASSWORD}"))
    )
}

impl Orthanc {
    fn start() -> Self {
        for (path, package) in [(ORTHANC, "orthanc"), (DICOMWEB_PLUGIN, "orthanc-dicomweb")] {
            assert!(
                Path::new(path).exists(),
                "the DICOMweb test needs a real Orthanc: apt-get install {package} (no {path})"
            );
        }
        let storage = tempfile::tempdir().expect("a folder for Orthanc");
        let port = free_port();
        let config = json!({
            "Name": "voxlight-test",
            "StorageDirectory": storage.path().join("db"),
            "IndexDirectory": storage.path().join("db"),
            "HttpPort": port,
            "DicomPort": free_port(),
            "RemoteAccessAllowed": false,
            "AuthenticationEnabled": true,
            "RegisteredUsers": { USER: PASSWORD },
            "Plugins": [DICOMWEB_PLUGIN],
            "DicomWeb": { "Enable": true, "Root": "/dicom-web/" }
        });
        let config_path = storage.path().join("orthanc.json");
        std::fs::write(&config_path, config.to_string()).expect("writing Orthanc's config");
        let child = Command::new(ORTHANC)
            .arg(&config_path)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("starting Orthanc");
        let orthanc = Orthanc {
            child,
            port,
            _storage: storage,
        };
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let answer = agent()
                .get(format!("{}/system", orthanc.url()))
                .header("Authorization", basic())
                .call();
            if answer.is_ok_and(|r| r.status() == 200) {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "Orthanc did not answer within 60 s"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        orthanc
    }

    fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    fn upload(&self, files: &[PathBuf]) {
        for file in files {
            let bytes = std::fs::read(file).expect("reading a slice");
            let response = agent()
                .post(format!("{}/instances", self.url()))
                .header("Authorization", basic())
                .send(&bytes[..])
                .expect("uploading to Orthanc");
            assert_eq!(response.status(), 200, "Orthanc refused {}", file.display());
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_series_from_a_pacs_arrives_with_progress_and_equals_the_local_one() {
    let series = shared_data().join("ct-chest-lidc");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&series)
        .expect("the chest series")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "dcm"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 128);
    let orthanc = tokio::task::spawn_blocking(move || {
        let orthanc = Orthanc::start();
        orthanc.upload(&files);
        orthanc
    })
    .await
    .unwrap();

    // Wrong credentials: the server does not start, and says why without the secret.
    let folder = tempfile::tempdir().unwrap();
    let wrong = folder.path().join("wrong");
    std::fs::write(&wrong, "radiology:not-the-password\n").unwrap();
    let refused = TestServer::start_with(ServerConfig {
        dicomweb: Some(DicomWebSource {
            url: format!("{}/dicom-web", orthanc.url()),
            credentials: Some(wrong),
        }),
        ..Default::default()
    })
    .await
    .err()
    .map(|e| format!("{e:#}"))
    .unwrap_or_default();
    assert!(refused.contains("401"), "{refused}");
    assert!(!refused.contains("not-the-password"), "{refused}");

    let credentials = folder.path().join("pacs");
    std::fs::write(
        &credentials,
        format!("# the PACS account\n{USER}:{PASSWORD}\n"),
    )
    .unwrap();
    let server = TestServer::start_with(ServerConfig {
        default_dataset: Some("phantom:sphere".into()),
        dicomweb: Some(DicomWebSource {
            url: format!("{}/dicom-web/", orthanc.url()),
            credentials: Some(credentials),
        }),
        ..Default::default()
    })
    .await
    .unwrap();
    let (_, listing) = server.get("/api/datasets").await;
    let listing: serde_json::Value = serde_json::from_str(&listing).unwrap();
    let remote: Vec<&str> = listing["datasets"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|d| d["kind"] == "dicomweb")
        .filter_map(|d| d["name"].as_str())
        .collect();
    assert_eq!(remote.len(), 1, "{listing}");
    let name = remote[0].to_owned();
    assert!(name.starts_with("dicomweb/1.3.6.1."), "{name}");

    let mut viewer = Client::connect(&server.ws_url()).await.unwrap();
    viewer
        .send_json(json!({"type": "hello", "protocol": 1, "viewport": {"width": 32, "height": 32}, "dataset": name}))
        .await
        .unwrap();
    let mut progress = Vec::new();
    let welcome = loop {
        match viewer.recv().await.unwrap() {
            Incoming::Text(message) => match *message {
                ServerMessage::Loading { done, total, .. } => progress.push((done, total)),
                welcome @ ServerMessage::Welcome { .. } => break welcome,
                other => panic!("expected loading or welcome, got {other:?}"),
            },
            Incoming::Frame(_) => panic!("a frame before the welcome"),
        }
    };
    assert!(
        progress.len() >= 2,
        "progress while the instances arrive: {progress:?}"
    );
    assert!(
        progress.windows(2).all(|w| w[0].0 <= w[1].0),
        "{progress:?}"
    );
    assert!(
        progress.iter().all(|&(_, total)| total == 128),
        "{progress:?}"
    );
    let ServerMessage::Welcome { dataset, .. } = welcome else {
        unreachable!()
    };
    let details = dataset.details.expect("details of the loaded series");
    assert_eq!(details.dims, [512, 512, 128]);
    assert_eq!(details.units, "HU");
    viewer.frame_where(|_| true).await.unwrap();

    // The fetched volume is the local series, voxel for voxel (same bytes, same loader).
    let catalog = server.state.catalog.clone();
    let fetched = tokio::task::spawn_blocking(move || catalog.load(&name))
        .await
        .unwrap()
        .unwrap();
    let local = voxlight_volumes::load(&series).unwrap();
    assert_eq!(fetched.dims, local.dims);
    assert_eq!(fetched.spacing, local.spacing);
    assert!(fetched.data == local.data, "voxels differ");
    for ([x, y, z], hu) in [
        ([160, 444, 54], -907.0),
        ([153, 212, 103], 78.0),
        ([261, 170, 23], 906.0),
    ] {
        assert_eq!(
            fetched.raw_value(x, y, z).round(),
            hu,
            "voxel ({x}, {y}, {z})"
        );
    }
    viewer.close().await;
    server.stop().await.unwrap();
}
