//! The `voxlight` binary as users call it: render, bad input, missing data folder.

use std::path::PathBuf;
use std::process::Command;

use voxlight_app::offline::read_pfm;

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("voxlight-cli-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn voxlight() -> Command {
    Command::new(env!("CARGO_BIN_EXE_voxlight"))
}

#[test]
fn render_writes_png_and_linear_pfm() {
    let dir = temp_dir("render");
    let scene = dir.join("scene.json");
    // Empty TF: every pixel is exactly the environment radiance.
    std::fs::write(
        &scene,
        r#"{"dataset":"phantom:sphere","tf":{"points":[]},"width":48,"height":32,"iterations":2,
            "lights":[{"kind":"environment","radiance":[0.25,0.5,0.75]}]}"#,
    )
    .unwrap();
    let (png, pfm) = (dir.join("out.png"), dir.join("out.pfm"));
    let output = voxlight()
        .args(["render", "--scene"])
        .arg(&scene)
        .arg("--out")
        .arg(&png)
        .arg("--pfm")
        .arg(&pfm)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "render failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));
    let (w, h, rgb) = read_pfm(&pfm).unwrap();
    assert_eq!((w, h), (48, 32));
    for px in rgb {
        for (got, want) in px.iter().zip([0.25f32, 0.5, 0.75]) {
            assert!((got - want).abs() < 1e-6, "{px:?}");
        }
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn bad_scene_files_fail_with_a_message() {
    let dir = temp_dir("bad");
    let cases = [
        ("missing.json", None, "reading"),
        (
            "typo.json",
            Some(r#"{"dataset":"phantom:sphere","widht":10}"#),
            "unknown field",
        ),
        (
            "dataset.json",
            Some(r#"{"dataset":"no/such/file.nrrd"}"#),
            "no/such/file.nrrd",
        ),
        (
            "viewport.json",
            Some(r#"{"dataset":"phantom:sphere","width":0}"#),
            "viewport",
        ),
        (
            "option.json",
            Some(
                r#"{"dataset":"phantom:sphere","technique":"photon","technique_options":{"photon":{"segments":99}}}"#,
            ),
            "photon.segments must be in [1, 32], got 99",
        ),
        (
            "option_typo.json",
            Some(r#"{"dataset":"phantom:sphere","technique_options":{"manylight":{"vls":10}}}"#),
            "unknown field `vls`",
        ),
    ];
    for (name, body, expected) in cases {
        let scene = dir.join(name);
        if let Some(body) = body {
            std::fs::write(&scene, body).unwrap();
        }
        let output = voxlight()
            .args(["render", "--scene"])
            .arg(&scene)
            .arg("--out")
            .arg(dir.join("x.png"))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{name} should fail");
        assert!(
            stderr.contains(expected),
            "{name}: stderr does not mention `{expected}`: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{name} panicked: {stderr}");
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn serve_refuses_a_missing_data_folder() {
    let output = voxlight()
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--data",
            "/definitely/not/here",
        ])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(
        stderr.contains("/definitely/not/here") && stderr.contains("does not exist"),
        "{stderr}"
    );
}

#[test]
fn no_adapter_names_the_package_to_install() {
    // Point the Vulkan loader at no driver at all: the only adapters wgpu could use vanish.
    let output = voxlight()
        .args(["serve", "--listen", "127.0.0.1:0"])
        .env("VK_ICD_FILENAMES", "/nonexistent/icd.json")
        .env("VK_DRIVER_FILES", "/nonexistent/icd.json")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(stderr.contains("mesa-vulkan-drivers"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}
