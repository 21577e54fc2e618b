//! Logs never carry patient data: a DICOM series whose headers name a patient is opened over
//! the protocol with every log level on, and the log output is searched for the name, id and
//! birth date.

use std::io::Write;
use std::sync::{Arc, Mutex};

use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use serde_json::json;
use voxlight_app::ServerConfig;
use voxlight_protocol::ServerMessage;
use voxlight_tests::{Client, TestServer, shared_data};

#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0
            .lock()
            .map_err(|_| std::io::Error::other("poisoned"))?
            .extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

const NAME: &str = "Doe^Jane^Quincy";
const PATIENT_ID: &str = "PHI-8841-27";
const BIRTH_DATE: &str = "19480317";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn logs_never_contain_patient_name_id_or_birth_date() {
    let captured = Captured::default();
    let writer = captured.clone();
    tracing_subscriber::fmt()
        .with_max_level(tracing::Level::TRACE)
        .with_writer(move || writer.clone())
        .with_ansi(false)
        .init();

    // Eight slices of the real chest CT, with identifying headers put back in.
    let data = tempfile::tempdir().unwrap();
    let series = data.path().join("study");
    std::fs::create_dir(&series).unwrap();
    let source = shared_data().join("ct-chest-lidc");
    let mut files: Vec<_> = std::fs::read_dir(&source)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .collect();
    files.sort();
    for (i, file) in files.iter().take(8).enumerate() {
        let mut object = dicom_object::open_file(file).unwrap();
        let put = |o: &mut dicom_object::DefaultDicomObject, tag, vr, value: &str| {
            o.put(DataElement::new(tag, vr, PrimitiveValue::from(value)));
        };
        put(&mut object, tags::PATIENT_NAME, VR::PN, NAME);
        put(&mut object, tags::PATIENT_ID, VR::LO, PATIENT_ID);
        put(&mut object, tags::PATIENT_BIRTH_DATE, VR::DA, BIRTH_DATE);
        object
            .write_to_file(series.join(format!("{i:03}.dcm")))
            .unwrap();
    }
    // A broken file too, so warnings and error paths log.
    std::fs::write(series.join("junk.dcm"), b"DICM but not really").unwrap();

    let server = TestServer::start_with(ServerConfig {
        data_dir: Some(data.path().to_owned()),
        default_dataset: Some("phantom:sphere".into()),
        preload: true,
        ..Default::default()
    })
    .await
    .unwrap();
    let mut client = Client::connect(&server.ws_url()).await.unwrap();
    let welcome = client
        .hello_with(
            json!({"type": "hello", "protocol": 1, "dataset": "study", "name": "Dr. Who",
            "viewport": {"width": 32, "height": 32}}),
        )
        .await
        .unwrap();
    let ServerMessage::Welcome { dataset, .. } = &welcome else {
        panic!("expected welcome, got {welcome:?}");
    };
    let shown = serde_json::to_string(dataset).unwrap();
    client.frame_where(|_| true).await.unwrap();
    client.send_text("not json".into()).await.unwrap();
    client.recv_text().await.unwrap();
    let listing = server.metrics().await;
    client.close().await;
    server.stop().await.unwrap();

    let log = String::from_utf8(captured.0.lock().unwrap().clone()).unwrap();
    assert!(
        log.contains("session opened") && log.contains("session="),
        "logs carry session ids: {log}"
    );
    for secret in [
        NAME,
        "Doe",
        "Jane",
        PATIENT_ID,
        BIRTH_DATE,
        "1948-03-17",
        "LIDC-IDRI",
    ] {
        assert!(!log.contains(secret), "the log contains `{secret}`");
        assert!(
            !shown.contains(secret),
            "dataset info contains `{secret}`: {shown}"
        );
        assert!(!listing.contains(secret), "metrics contain `{secret}`");
    }
}
