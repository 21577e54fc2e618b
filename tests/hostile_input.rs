//! Property tests over everything the server reads from outside: client messages through the
//! server's decode and validation, binary frames, scene files, and volume files through every
//! loader. CI's stand-in for the fuzz targets in `fuzz/` (which need nightly and hours); the
//! loader seeds are the fuzz seeds (`fuzz/seeds/`, headers of the real data with small slices
//! of it). No GPU. Properties: nothing panics; a message the server accepts is finite and in
//! range (its echo to other viewers parses back equal); a loader allocates in proportion to
//! the file it reads, never to the sizes a header declares.

#[path = "../fuzz/fuzz_targets/raw_layout.rs"]
mod raw_layout;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use proptest::prelude::*;
use proptest::test_runner::Config;
use serde_json::{Value, json};
use voxlight_app::session::validate_message;
use voxlight_protocol::{
    Camera, ClientMessage, Light, MAX_MESSAGE_BYTES, Scene as SceneFile, ServerMessage, TfPoint,
    TransferFunction, Viewport, join_frame, split_frame,
};
use voxlight_volumes::Volume;

// ---------- allocation accounting ----------

/// Counts the bytes live on each thread and their peak, so a property can bound what one call
/// allocates (other tests' threads do not disturb it).
struct Counting;

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn grew(bytes: usize) {
    let _ = LIVE.try_with(|live| {
        let now = live.get().saturating_add(bytes);
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

fn shrank(bytes: usize) {
    let _ = LIVE.try_with(|live| live.set(live.get().saturating_sub(bytes)));
}

// SAFETY: every call is forwarded to the system allocator unchanged; the bookkeeping only
// touches thread-local cells (const-initialised, so it never allocates).
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is passed on as is.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as for `alloc`.
        unsafe { System.dealloc(ptr, layout) };
        shrank(layout.size());
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as for `alloc`.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            shrank(layout.size());
            grew(new_size);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `f`; returns its result and the most bytes it had allocated at once on this thread.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|peak| peak.set(base));
    let result = f();
    (result, PEAK.with(Cell::get).saturating_sub(base))
}

#[test]
fn allocation_accounting_sees_what_a_call_allocates() {
    let (len, peak) = peak_of(|| std::hint::black_box(vec![1u8; 10 << 20]).len());
    assert_eq!(len, 10 << 20);
    assert!((10 << 20..11 << 20).contains(&peak), "{peak}");
    let (_, nothing) = peak_of(|| 1 + 1);
    assert_eq!(nothing, 0);
}

// ---------- client messages ----------

const TAGS: &[&str] = &[
    "hello",
    "ack",
    "name",
    "dataset",
    "camera",
    "tf",
    "lights",
    "technique",
    "viewport",
    "params",
    "quality",
];

const FIELDS: &[&str] = &[
    "type",
    "protocol",
    "session",
    "token",
    "viewport",
    "dataset",
    "technique",
    "technique_options",
    "name",
    "max_in_flight",
    "seq",
    "eye",
    "target",
    "up",
    "fov_deg",
    "points",
    "value",
    "color",
    "opacity",
    "lights",
    "kind",
    "direction",
    "irradiance",
    "position",
    "intensity",
    "radiance",
    "options",
    "width",
    "height",
    "density_scale",
    "g",
    "exposure",
    "jpeg_quality",
    "iterations",
    "photon",
    "manylight",
    "passes",
    "bounces",
    "radius",
    "virtual_lights",
    "gamma",
];

/// Numbers at and beyond every documented edge, and beyond f32.
const EDGES: &[f64] = &[
    0.0,
    -0.0,
    1.0,
    -1.0,
    0.5,
    0.99,
    -0.99,
    1e-45,
    1e-30,
    3.4e38,
    3.5e38,
    1e39,
    -1e39,
    1e300,
    -1e300,
    100.0,
    101.0,
    179.0,
    255.0,
    256.0,
    300.0,
    4096.0,
    4097.0,
    65536.0,
    65537.0,
    1e5,
    1e10,
    4294967295.0,
    4294967296.0,
    1.8e19,
];

fn json_leaf() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        (0u32..300).prop_map(Value::from),
        prop::sample::select(EDGES).prop_map(|f| json!(f)),
        any::<f64>().prop_filter_map("JSON has no NaN or infinity", |f| f
            .is_finite()
            .then(|| json!(f))),
        prop::sample::select(TAGS).prop_map(Value::from),
        "[a-z_:/.]{0,12}".prop_map(Value::String),
    ]
}

fn json_value() -> impl Strategy<Value = Value> {
    json_leaf().prop_recursive(4, 48, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::btree_map(prop::sample::select(FIELDS), inner, 0..6).prop_map(|m| {
                Value::Object(m.into_iter().map(|(k, v)| (k.to_owned(), v)).collect())
            }),
        ]
    })
}

/// An object with a known `type` and arbitrary known fields.
fn json_message() -> impl Strategy<Value = Value> {
    (
        prop::sample::select(TAGS),
        prop::collection::btree_map(prop::sample::select(FIELDS), json_value(), 0..6),
    )
        .prop_map(|(tag, fields)| {
            let mut object: serde_json::Map<String, Value> =
                fields.into_iter().map(|(k, v)| (k.to_owned(), v)).collect();
            object.insert("type".into(), tag.into());
            Value::Object(object)
        })
}

/// Valid messages of every type (from docs/protocol.md), the starting points of mutations.
fn seed_messages() -> Vec<Value> {
    vec![
        json!({"type": "hello", "protocol": 1, "viewport": {"width": 960, "height": 720}, "dataset": "phantom:sphere", "technique": "raymarch", "max_in_flight": 2}),
        json!({"type": "hello", "protocol": 1, "session": "6c1f0e1e", "name": "Ada", "technique_options": {"photon": {"passes": 4, "radius": 0.05}}}),
        json!({"type": "ack", "seq": 41}),
        json!({"type": "name", "name": "Ada"}),
        json!({"type": "dataset", "name": "nrrd/tooth.nrrd"}),
        json!({"type": "camera", "eye": [0.0, -2.4, 0.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "fov_deg": 30.0}),
        json!({"type": "tf", "points": [
            {"value": 0.0, "color": [0.1, 0.2, 0.9], "opacity": 0.0},
            {"value": 0.5, "color": [1.0, 1.0, 1.0], "opacity": 0.25},
            {"value": 1.0, "color": [0.9, 0.8, 0.7], "opacity": 0.8}]}),
        json!({"type": "tf", "points": []}),
        json!({"type": "lights", "lights": [
            {"kind": "directional", "direction": [0.35, 0.75, -0.55], "irradiance": [3.2, 3.1, 2.9]},
            {"kind": "point", "position": [0.0, 0.0, 2.0], "intensity": [3.0, 3.0, 3.0]},
            {"kind": "environment", "radiance": [0.1, 0.11, 0.13]}]}),
        json!({"type": "technique", "name": "manylight", "options": {"manylight": {"virtual_lights": 1000, "transmittance": "ray_marched", "vsl_radius": 0.01}}}),
        json!({"type": "technique", "name": "irradiance", "options": {"irradiance": {"locking": "screen", "max_radius_voxels": 2.0, "gamma": 0.1}}}),
        json!({"type": "viewport", "width": 64, "height": 48}),
        json!({"type": "params", "density_scale": 60.0, "g": 0.3, "exposure": 1.5}),
        json!({"type": "quality", "jpeg_quality": 70, "iterations": 256}),
    ]
}

/// Replaces the `n`th leaf (in a depth-first walk, modulo the leaf count) with `leaf`.
fn replace_leaf(value: &mut Value, n: usize, leaf: Value) {
    fn count(v: &Value) -> usize {
        match v {
            Value::Array(a) if !a.is_empty() => a.iter().map(count).sum(),
            Value::Object(o) if !o.is_empty() => o.values().map(count).sum(),
            _ => 1,
        }
    }
    fn walk(v: &mut Value, n: &mut usize, leaf: &mut Option<Value>) {
        match v {
            Value::Array(a) if !a.is_empty() => a.iter_mut().for_each(|x| walk(x, n, leaf)),
            Value::Object(o) if !o.is_empty() => o.values_mut().for_each(|x| walk(x, n, leaf)),
            _ => {
                if *n == 0
                    && let Some(new) = leaf.take()
                {
                    *v = new;
                }
                *n = n.wrapping_sub(1);
            }
        }
    }
    let mut n = n % count(value);
    walk(value, &mut n, &mut Some(leaf));
}

/// Decodes and validates as the server does; an accepted message must come back equal from
/// its echo (so no NaN or infinity was accepted: they serialize as `null`).
fn decode_and_validate(bytes: &[u8]) -> Option<bool> {
    let message = serde_json::from_slice::<ClientMessage>(bytes).ok()?;
    let accepted = validate_message(&message).is_ok();
    if accepted {
        check_echo(&message);
    }
    Some(accepted)
}

fn check_echo(message: &ClientMessage) {
    let echo = serde_json::to_string(message).expect("an accepted message serializes");
    let back: ClientMessage = serde_json::from_str(&echo)
        .unwrap_or_else(|e| panic!("the echo of an accepted message does not parse ({e}): {echo}"));
    assert_eq!(
        &back, message,
        "the echo changed an accepted message: {echo}"
    );
    if let ClientMessage::Tf(tf) = message {
        let lut = voxlight_engine::tf::bake(tf);
        assert!(lut.iter().flatten().all(|x| x.is_finite()));
    }
}

fn any_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        prop::num::f32::ANY,
        -2.0f32..2.0,
        prop::sample::select(vec![
            0.0f32,
            1.0,
            -0.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MAX,
            f32::MIN_POSITIVE,
            0.99,
            179.0,
            1e5,
            1e4,
        ]),
    ]
}

fn vec3() -> impl Strategy<Value = [f32; 3]> {
    [any_f32(), any_f32(), any_f32()]
}

fn any_u32() -> impl Strategy<Value = u32> {
    prop_oneof![
        any::<u32>(),
        0u32..10,
        prop::sample::select(vec![4095u32, 4096, 4097, 65536, 65537, u32::MAX]),
    ]
}

/// Typed messages with any numbers at all (NaN and infinities included): what a client
/// library that skips JSON could hand the server's validation.
fn typed_message() -> impl Strategy<Value = ClientMessage> {
    let light = prop_oneof![
        (vec3(), vec3()).prop_map(|(direction, irradiance)| Light::Directional {
            direction,
            irradiance
        }),
        (vec3(), vec3()).prop_map(|(position, intensity)| Light::Point {
            position,
            intensity
        }),
        vec3().prop_map(|radiance| Light::Environment { radiance }),
    ];
    let point = (any_f32(), vec3(), any_f32()).prop_map(|(value, color, opacity)| TfPoint {
        value,
        color,
        opacity,
    });
    prop_oneof![
        (vec3(), vec3(), vec3(), any_f32()).prop_map(|(eye, target, up, fov_deg)| {
            ClientMessage::Camera(Camera {
                eye,
                target,
                up,
                fov_deg,
            })
        }),
        prop::collection::vec(point, 0..260)
            .prop_map(|points| ClientMessage::Tf(TransferFunction { points })),
        prop::collection::vec(light, 0..18).prop_map(|lights| ClientMessage::Lights { lights }),
        (any_u32(), any_u32())
            .prop_map(|(width, height)| ClientMessage::Viewport(Viewport { width, height })),
        (
            prop::option::of(any_f32()),
            prop::option::of(any_f32()),
            prop::option::of(any_f32())
        )
            .prop_map(|(density_scale, g, exposure)| ClientMessage::Params {
                density_scale,
                g,
                exposure
            }),
        (prop::option::of(any::<u8>()), prop::option::of(any_u32())).prop_map(
            |(jpeg_quality, iterations)| ClientMessage::Quality {
                jpeg_quality,
                iterations
            }
        ),
        prop::option::of(any_u32()).prop_map(|max_in_flight| ClientMessage::Hello {
            protocol: 1,
            session: None,
            token: None,
            viewport: None,
            dataset: None,
            technique: None,
            technique_options: None,
            name: None,
            max_in_flight,
        }),
    ]
}

/// Byte-level damage to a text: flips, cuts, insertions of awkward tokens.
fn damage() -> impl Strategy<Value = Vec<(usize, u8, usize)>> {
    prop::collection::vec((any::<usize>(), 0u8..6, any::<usize>()), 1..5)
}

const TOKENS: &[&str] = &[
    "1e39",
    "-1",
    "1e400",
    "NaN",
    "null",
    "\"\"",
    "[]",
    "{}",
    "4294967296",
    "-0",
    "[[[[",
    "\u{0}",
    "\"\\ud800\"",
    "0.99",
    "true",
];

fn apply_damage(mut bytes: Vec<u8>, edits: &[(usize, u8, usize)]) -> Vec<u8> {
    for &(at, op, arg) in edits {
        let at = if bytes.is_empty() {
            0
        } else {
            at % bytes.len()
        };
        match op {
            0 if !bytes.is_empty() => bytes[at] ^= 1 << (arg % 8),
            1 => bytes.truncate(at),
            2 => {
                let token = TOKENS[arg % TOKENS.len()].as_bytes();
                bytes.splice(at..at, token.iter().copied());
            }
            3 if !bytes.is_empty() => {
                bytes.remove(at);
            }
            4 if !bytes.is_empty() => bytes[at] = arg as u8,
            _ => {
                // Replace a run of digits at or after `at` with a token.
                if let Some(start) = bytes[at..].iter().position(u8::is_ascii_digit) {
                    let start = at + start;
                    let end = bytes[start..]
                        .iter()
                        .position(|c| !c.is_ascii_digit() && *c != b'.')
                        .map_or(bytes.len(), |e| start + e);
                    let token = TOKENS[arg % TOKENS.len()].as_bytes();
                    bytes.splice(start..end, token.iter().copied());
                }
            }
        }
    }
    bytes
}

/// `cases` random cases; failures are not written to a regressions file (cases worth keeping
/// become explicit tests, such as `a_joining_hello_is_range_checked_too`).
fn config(cases: u32) -> Config {
    Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    }
}

/// Found by `valid_messages_with_one_value_replaced`: a `hello` that joins a session passed
/// `validate_message` with options out of range (they were only checked for new sessions).
#[test]
fn a_joining_hello_is_range_checked_too() {
    for hello in [
        json!({"type": "hello", "protocol": 1, "session": "6c1f0e1e", "technique_options": {"photon": {"passes": 4, "radius": 3.5e38}}}),
        json!({"type": "hello", "protocol": 1, "session": "6c1f0e1e", "viewport": {"width": 0, "height": 1}}),
    ] {
        let message: ClientMessage = serde_json::from_value(hello.clone()).expect("parses");
        assert!(validate_message(&message).is_err(), "{hello} was accepted");
    }
}

proptest! {
    #![proptest_config(config(2048))]

    #[test]
    fn any_bytes_decode_without_panic(bytes in prop::collection::vec(any::<u8>(), 0..1024)) {
        decode_and_validate(&bytes);
        let _ = serde_json::from_slice::<ServerMessage>(&bytes);
        if let Some((_, image)) = split_frame(&bytes) {
            prop_assert!(image.len() + 4 <= bytes.len());
        }
    }

    #[test]
    fn random_json_messages_decode_and_validate(message in json_message()) {
        let text = message.to_string();
        prop_assume!(text.len() <= MAX_MESSAGE_BYTES);
        decode_and_validate(text.as_bytes());
    }

    #[test]
    fn valid_messages_with_one_value_replaced(
        seed in 0..seed_messages().len(),
        edits in prop::collection::vec((any::<usize>(), json_leaf()), 1..4),
    ) {
        let mut message = seed_messages()[seed].clone();
        for (at, leaf) in edits {
            replace_leaf(&mut message, at, leaf);
        }
        decode_and_validate(message.to_string().as_bytes());
    }

    #[test]
    fn valid_messages_with_damaged_bytes(seed in 0..seed_messages().len(), edits in damage()) {
        let bytes = apply_damage(seed_messages()[seed].to_string().into_bytes(), &edits);
        decode_and_validate(&bytes);
    }

    #[test]
    fn typed_messages_with_any_numbers(message in typed_message()) {
        if validate_message(&message).is_ok() {
            check_echo(&message);
        }
    }

    #[test]
    fn frames_with_damaged_length_or_metadata(
        width in any::<u32>(),
        image in prop::collection::vec(any::<u8>(), 0..64),
        edits in damage(),
    ) {
        let meta = voxlight_protocol::FrameMeta {
            seq: 7,
            format: voxlight_protocol::FrameFormat::Jpeg,
            width,
            height: 2,
            technique: "raymarch".into(),
            iteration: 1,
            target_iterations: 8,
            converged: false,
            lossless: false,
            quality: Some(85),
            scene_version: 3,
            preview: false,
            resolution_scale: 0.5,
            preview_match: None,
            render_ms: 1.0,
            encode_ms: 0.5,
            details: Default::default(),
        };
        let joined = join_frame(&meta, &image);
        let (back, back_image) = split_frame(&joined).expect("a joined frame splits");
        prop_assert_eq!(back, meta);
        prop_assert_eq!(back_image, &image[..]);
        let damaged = apply_damage(joined, &edits);
        if let Some((_, rest)) = split_frame(&damaged) {
            prop_assert!(rest.len() + 4 <= damaged.len());
        }
    }
}

// ---------- scene files ----------

fn tiny_volume() -> &'static Volume {
    static VOLUME: OnceLock<Volume> = OnceLock::new();
    VOLUME.get_or_init(|| {
        let data = (0..4 * 3 * 2).map(|i| (i * 2700) as u16).collect();
        Volume::from_normalized("tiny", [4, 3, 2], [1.0, 0.5, 2.0], data).expect("volume")
    })
}

fn seed_scenes() -> Vec<Value> {
    let cornell: Value = serde_json::from_str(include_str!("../docs/scenes/cornell.json"))
        .expect("docs/scenes/cornell.json parses");
    vec![
        cornell,
        json!({"dataset": "phantom:sphere"}),
        json!({"dataset": "nrrd/tooth.nrrd", "camera": {"eye": [2, -1, 0.5], "target": [0, 0, 0], "up": [0, 0, 1], "fov_deg": 35},
               "tf": {"points": [{"value": 0.2, "color": [1, 1, 1], "opacity": 0.0}]},
               "lights": [{"kind": "environment", "radiance": [0.25, 0.5, 0.75]}],
               "technique": "pathtrace", "technique_options": {"photon": {"bounces": 2}},
               "density_scale": 30, "g": -0.2, "exposure": 2, "width": 48, "height": 32, "iterations": 2, "seed": 9}),
    ]
}

fn check_scene(bytes: &[u8]) {
    let Ok(file) = serde_json::from_slice::<SceneFile>(bytes) else {
        return;
    };
    if let Ok(scene) = voxlight_app::offline::engine_scene(&file, tiny_volume()) {
        assert!(scene.validate().is_ok());
        assert!(scene.target_iterations >= 1);
    }
}

proptest! {
    #![proptest_config(config(1024))]

    #[test]
    fn scene_files_with_values_replaced(
        seed in 0..seed_scenes().len(),
        edits in prop::collection::vec((any::<usize>(), json_leaf()), 1..4),
    ) {
        let mut scene = seed_scenes()[seed].clone();
        for (at, leaf) in edits {
            replace_leaf(&mut scene, at, leaf);
        }
        check_scene(scene.to_string().as_bytes());
    }

    #[test]
    fn scene_files_with_damaged_bytes(seed in 0..seed_scenes().len(), edits in damage()) {
        check_scene(&apply_damage(seed_scenes()[seed].to_string().into_bytes(), &edits));
    }
}

// ---------- volume files ----------

fn seeds_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/seeds")
}

/// The fuzz seeds of one loader target: (file name, bytes).
fn loader_seeds(target: &str) -> Vec<(String, Vec<u8>)> {
    let dir = seeds_dir().join(target);
    let mut seeds: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| {
            let path = entry.expect("seed entry").path();
            let name = path
                .file_name()
                .expect("seed name")
                .to_string_lossy()
                .into_owned();
            (name, std::fs::read(&path).expect("seed bytes"))
        })
        .collect();
    seeds.sort();
    assert!(!seeds.is_empty(), "no seeds in {}", dir.display());
    seeds
}

/// A folder with the companion files detached headers name (as the fuzz harnesses write).
fn scratch() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().expect("temp dir");
        for name in ["tooth.raw", "data.raw.gz"] {
            std::fs::copy(
                seeds_dir().join("companions").join(name),
                dir.path().join(name),
            )
            .expect("companion file");
        }
        let img: Vec<u8> = (0..8192u32).map(|i| (i * 31 % 253) as u8).collect();
        std::fs::write(dir.path().join("pair.img"), img).expect("pair.img");
        dir
    })
    .path()
}

/// The name a loader target gives a file (as the fuzz harness does).
fn file_name(target: &str, bytes: &[u8], case: u64) -> String {
    let stem = format!("case{case}-{:?}", std::thread::current().id())
        .replace(|c: char| !c.is_ascii_alphanumeric(), "_");
    match target {
        "load_nrrd" => format!("{stem}.nrrd"),
        "load_vti" => format!("{stem}.vti"),
        "load_dicom" => format!("{stem}.dcm"),
        _ if bytes.starts_with(&[0x1f, 0x8b]) => format!("{stem}.nii.gz"),
        // A `ni1` header reads the `.img` beside it (`check_load` writes one).
        _ if bytes.get(344..348) == Some(b"ni1\0") => format!("{stem}.hdr"),
        _ => format!("{stem}.nii"),
    }
}

/// Most bytes a load may allocate for a file of `len` bytes: a fixed allowance (read buffers,
/// the first reservation of samples, tables) plus a multiple of the input that covers the
/// widest decoded type and the compression ratio deflate can reach (about 1000:1).
fn allocation_bound(len: usize) -> usize {
    (24 << 20) + 1100 * len
}

fn check_load(target: &str, bytes: &[u8], case: u64) -> Result<(), TestCaseError> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static SERIAL: AtomicU64 = AtomicU64::new(0);
    let name = file_name(
        target,
        bytes,
        case ^ (SERIAL.fetch_add(1, Ordering::Relaxed) << 20),
    );
    let path = scratch().join(&name);
    std::fs::write(&path, bytes).expect("scratch file");
    let image = path.with_extension("img");
    if name.ends_with(".hdr") {
        std::fs::copy(scratch().join("pair.img"), &image).expect("pair image");
    }
    let (result, peak) = peak_of(|| voxlight_volumes::load(&path).map(|v| v.voxel_count()));
    let _ = std::fs::remove_file(&path);
    let _ = std::fs::remove_file(&image);
    prop_assert!(
        peak <= allocation_bound(bytes.len()),
        "loading a {}-byte {target} file allocated {peak} bytes ({result:?})",
        bytes.len()
    );
    if let Err(e) = result {
        prop_assert!(!e.to_string().is_empty());
    }
    Ok(())
}

fn loader_property(target: &'static str) -> impl Strategy<Value = Vec<u8>> {
    let seeds = loader_seeds(target);
    (
        0..seeds.len(),
        damage(),
        prop::collection::vec(any::<(usize, u8)>(), 0..4),
    )
        .prop_map(move |(k, edits, flips)| {
            let mut bytes = seeds[k].1.clone();
            // Header bytes are where the damage matters most: bias some flips to the first 512.
            for (at, mask) in flips {
                let span = bytes.len().clamp(1, 512);
                if let Some(b) = bytes.get_mut(at % span) {
                    *b ^= mask;
                }
            }
            apply_damage(bytes, &edits)
        })
}

proptest! {
    #![proptest_config(config(400))]

    #[test]
    fn nrrd_files_damaged(bytes in loader_property("load_nrrd"), case in any::<u64>()) {
        check_load("load_nrrd", &bytes, case)?;
    }

    #[test]
    fn nifti_files_damaged(bytes in loader_property("load_nifti"), case in any::<u64>()) {
        check_load("load_nifti", &bytes, case)?;
    }

    #[test]
    fn vti_files_damaged(bytes in loader_property("load_vti"), case in any::<u64>()) {
        check_load("load_vti", &bytes, case)?;
    }

    #[test]
    fn dicom_files_damaged(bytes in loader_property("load_dicom"), case in any::<u64>()) {
        check_load("load_dicom", &bytes, case)?;
    }

    #[test]
    fn truncated_seeds(target in prop::sample::select(vec!["load_nrrd", "load_nifti", "load_vti", "load_dicom"]),
                       k in any::<usize>(), cut in any::<usize>(), case in any::<u64>()) {
        let seeds = loader_seeds(target);
        let bytes = &seeds[k % seeds.len()].1;
        check_load(target, &bytes[..cut % (bytes.len() + 1)], case)?;
    }
}

/// Headers declaring up to 2³¹ voxels of up to 8 bytes (16 GiB) over a few bytes of data, raw
/// and compressed: refused, having allocated next to nothing.
fn declared_sizes() -> impl Strategy<Value = ([u64; 3], usize, bool)> {
    // Each edge below 1291 keeps the product within 2³¹ (beyond it is a plain size error).
    (
        [1u64..1291, 1u64..1291, 1u64..1291],
        0usize..4,
        any::<bool>(),
    )
}

proptest! {
    #![proptest_config(config(256))]

    #[test]
    fn declared_sizes_beyond_the_data_allocate_nothing_big(
        (dims, ty, compressed) in declared_sizes(),
        data in prop::collection::vec(any::<u8>(), 0..256),
    ) {
        use std::io::Write;
        let voxels: u64 = dims.iter().product();
        let size = [1u64, 2, 4, 8][ty];
        prop_assume!(voxels * size > data.len() as u64);
        let gz = |b: &[u8]| {
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            e.write_all(b).expect("gzip");
            e.finish().expect("gzip")
        };
        let payload = if compressed { gz(&data) } else { data.clone() };
        // NRRD.
        let nrrd_type = ["uint8", "int16", "float", "double"][ty];
        let mut nrrd = format!(
            "NRRD0004\ntype: {nrrd_type}\ndimension: 3\nsizes: {} {} {}\nendian: little\nencoding: {}\n\n",
            dims[0], dims[1], dims[2], if compressed { "gzip" } else { "raw" }
        ).into_bytes();
        nrrd.extend_from_slice(&payload);
        // NIfTI-1 (dims fit i16 only up to 32767: larger ones are their own error).
        let mut nii = vec![0u8; 352];
        nii[0..4].copy_from_slice(&348i32.to_le_bytes());
        for (i, d) in [3u64, dims[0], dims[1], dims[2], 1, 1, 1, 1].iter().enumerate() {
            nii[40 + 2 * i..42 + 2 * i].copy_from_slice(&(*d as i16).to_le_bytes());
        }
        let code: i16 = [2, 4, 16, 64][ty];
        nii[70..72].copy_from_slice(&code.to_le_bytes());
        nii[72..74].copy_from_slice(&((size * 8) as i16).to_le_bytes());
        nii[76..80].copy_from_slice(&1f32.to_le_bytes());
        nii[108..112].copy_from_slice(&352f32.to_le_bytes());
        nii[344..348].copy_from_slice(b"n+1\0");
        nii.extend_from_slice(&data);
        let nii = if compressed { gz(&nii) } else { nii };
        // VTI, appended raw with a byte count that matches what it declares.
        let vtk_type = ["UInt8", "Int16", "Float32", "Float64"][ty];
        let mut vti = format!(
            "<VTKFile type=\"ImageData\" byte_order=\"LittleEndian\" header_type=\"UInt64\">\
             <ImageData WholeExtent=\"0 {} 0 {} 0 {}\" Spacing=\"1 1 1\"><Piece><PointData>\
             <DataArray type=\"{vtk_type}\" format=\"appended\" offset=\"0\"/></PointData></Piece>\
             </ImageData><AppendedData encoding=\"raw\">_",
            dims[0] - 1, dims[1] - 1, dims[2] - 1
        ).into_bytes();
        vti.extend_from_slice(&(voxels * size).to_le_bytes());
        vti.extend_from_slice(&data);
        for (target, bytes) in [("load_nrrd", nrrd), ("load_nifti", nii), ("load_vti", vti)] {
            let name = file_name(target, &bytes, voxels);
            let path = scratch().join(name);
            std::fs::write(&path, &bytes).expect("scratch file");
            let (result, peak) = peak_of(|| voxlight_volumes::load_raw(&path).map(|r| r.voxel_count()));
            let _ = std::fs::remove_file(&path);
            prop_assert!(result.is_err(), "{target}: {dims:?} × {size} B from {} bytes loaded", data.len());
            prop_assert!(
                peak <= (4 << 20) + 64 * bytes.len(),
                "{target}: {dims:?} × {size} B over {} bytes allocated {peak} bytes before refusing",
                bytes.len()
            );
        }
    }
}

proptest! {
    #![proptest_config(config(256))]

    #[test]
    fn raw_files_with_any_layout(
        dims in [any_u32(), any_u32(), any_u32()],
        ty in 0usize..8,
        big_endian in any::<bool>(),
        spacing in vec3(),
        header_bytes in prop_oneof![0u64..64, any::<u64>()],
        data in prop::collection::vec(any::<u8>(), 0..512),
    ) {
        use voxlight_volumes::{Endian, SampleType, load_raw_file};
        let sample = [
            SampleType::U8, SampleType::I8, SampleType::U16, SampleType::I16,
            SampleType::U32, SampleType::I32, SampleType::F32, SampleType::F64,
        ][ty];
        let endian = if big_endian { Endian::Big } else { Endian::Little };
        let path = scratch().join(format!("{:?}.raw", std::thread::current().id()).replace(|c: char| !c.is_ascii_alphanumeric() && c != '.', "_"));
        std::fs::write(&path, &data).expect("scratch file");
        let (result, peak) = peak_of(|| load_raw_file(&path, dims, sample, endian, spacing, header_bytes));
        let _ = std::fs::remove_file(&path);
        let needed = dims.iter().map(|&d| d as u128).product::<u128>() * sample.size() as u128
            + header_bytes as u128;
        if needed > data.len() as u128 {
            prop_assert!(result.is_err(), "{dims:?} {sample} + {header_bytes} from {} bytes", data.len());
            prop_assert!(peak <= 64 << 10, "refusing allocated {peak} bytes");
        }
        if let Ok(raw) = result {
            prop_assert_eq!(raw.samples.len(), raw.voxel_count());
            let volume = raw.normalize("raw");
            prop_assert!(volume.world_extent().iter().all(|e| e.is_normal() && *e <= 1.0));
        }
    }
}

/// Inputs that crashed a fuzz target (`fuzz/regressions/<target>/`), replayed through the
/// same loaders: each must give a value or an error, never a panic.
#[test]
fn fuzz_regressions_replay() {
    let root = seeds_dir().join("../regressions");
    let mut replayed = 0;
    for target in ["load_nrrd", "load_nifti", "load_vti", "load_dicom"] {
        let Ok(entries) = std::fs::read_dir(root.join(target)) else {
            continue;
        };
        for entry in entries {
            let bytes = std::fs::read(entry.expect("regression entry").path()).expect("bytes");
            check_load(target, &bytes, replayed).expect("within bounds");
            replayed += 1;
        }
    }
    if let Ok(entries) = std::fs::read_dir(root.join("load_raw")) {
        for entry in entries {
            let bytes = std::fs::read(entry.expect("regression entry").path()).expect("bytes");
            replay_raw(&bytes);
            replayed += 1;
        }
    }
    assert!(
        replayed > 0,
        "no regressions found under {}",
        root.display()
    );
}

/// Replays a kept `load_raw` fuzz input, read as the fuzz target reads it.
fn replay_raw(data: &[u8]) {
    use voxlight_volumes::load_raw_file;
    let Some((layout, body)) = raw_layout::raw_layout(data) else {
        return;
    };
    let path = scratch().join("replay.raw");
    std::fs::write(&path, body).expect("scratch file");
    if let Ok(raw) = load_raw_file(
        &path,
        layout.dims,
        layout.sample,
        layout.endian,
        layout.spacing,
        layout.header_bytes,
    ) {
        let volume = raw.normalize("replay");
        assert!(
            volume
                .world_extent()
                .iter()
                .all(|e| e.is_normal() && *e <= 1.0)
        );
    }
}
