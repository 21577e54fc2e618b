//! Scene files of `voxlight render`: parsed as `render` parses them, then turned into the
//! engine's scene and validated by `offline::engine_scene` (over a tiny in-memory volume, so
//! no file or phantom is opened).

#![no_main]

use std::sync::OnceLock;

use libfuzzer_sys::fuzz_target;
use voxlight_protocol::Scene as SceneFile;
use voxlight_volumes::Volume;

fn volume() -> &'static Volume {
    static VOLUME: OnceLock<Volume> = OnceLock::new();
    VOLUME.get_or_init(|| {
        let data = (0..4 * 3 * 2).map(|i| (i * 2700) as u16).collect();
        Volume::from_normalized("fuzz", [4, 3, 2], [1.0, 0.5, 2.0], data).expect("volume")
    })
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(file) = serde_json::from_str::<SceneFile>(text) else {
        return;
    };
    if let Ok(scene) = voxlight_app::offline::engine_scene(&file, volume()) {
        assert!(scene.validate().is_ok());
        assert!(scene.target_iterations >= 1);
    }
});
