//! Every message on the voxlight wire, and the scene file format (which uses the same field
//! names). Types only: no logic beyond serde attributes, defaults and overlaying options.
//!
//! Text messages are JSON objects tagged by `"type"`. Frames are binary messages: a 4-byte
//! little-endian length `N`, then `N` bytes of UTF-8 JSON [`FrameMeta`], then the encoded image.
//! `docs/protocol.md` documents all of it for client authors.

use serde::{Deserialize, Serialize};

mod options;
pub use options::*;

/// Version a client announces in `hello`; the server refuses others with `protocol_version`.
pub const PROTOCOL_VERSION: u32 = 1;

/// Largest text message the server accepts, in bytes.
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024;

/// Messages per second a connection may send on average (bursts up to twice that); the
/// rest are dropped with a `rate_limited` error.
pub const MAX_MESSAGES_PER_SECOND: u32 = 120;

/// Largest viewport edge in pixels.
pub const MAX_VIEWPORT_EDGE: u32 = 4096;

/// Most points a transfer function may have.
pub const MAX_TF_POINTS: usize = 256;

/// Most lights a scene may have.
pub const MAX_LIGHTS: usize = 16;

/// Most viewers one shared session may have.
pub const MAX_VIEWERS_PER_SESSION: usize = 32;

/// Longest viewer display name, in characters.
pub const MAX_NAME_CHARS: usize = 64;

/// Largest `max_in_flight` a client may ask for.
pub const MAX_FRAMES_IN_FLIGHT: u32 = 8;

/// Image size in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Viewport {
    pub width: u32,
    pub height: u32,
}

impl Default for Viewport {
    fn default() -> Self {
        Self {
            width: 512,
            height: 512,
        }
    }
}

/// Pinhole camera. `right = normalize(forward × up)`, image row 0 is the top.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub eye: [f32; 3],
    pub target: [f32; 3],
    pub up: [f32; 3],
    /// Vertical field of view in degrees.
    pub fov_deg: f32,
}

impl Default for Camera {
    /// Looks at the volume from world −y with +z up: for a CT in patient (LPS) coordinates this
    /// is an anterior view, head up.
    fn default() -> Self {
        Self {
            eye: [0.0, -2.4, 0.0],
            target: [0.0, 0.0, 0.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 30.0,
        }
    }
}

/// One control point of a transfer function.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TfPoint {
    /// Normalized data value in [0, 1].
    pub value: f32,
    /// Albedo, linear RGB in [0, 1].
    pub color: [f32; 3],
    /// Opacity in [0, 1]; extinction is `density_scale · opacity` per world unit.
    pub opacity: f32,
}

/// Piecewise linear between points (sorted by value), constant beyond the first and last.
/// No points means fully transparent.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TransferFunction {
    pub points: Vec<TfPoint>,
}

/// A light of the physical model (DESIGN.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Light {
    /// Parallel light. `direction` is the direction the light travels (from the light into the
    /// scene); `irradiance` is measured on a plane facing the light.
    Directional {
        direction: [f32; 3],
        irradiance: [f32; 3],
    },
    /// Isotropic point light with radiant `intensity`: irradiance I/d² at distance d.
    Point {
        position: [f32; 3],
        intensity: [f32; 3],
    },
    /// Uniform radiance from every direction; also the background.
    Environment { radiance: [f32; 3] },
}

/// Default lighting: a key light from the upper front left plus a dim environment.
pub fn default_lights() -> Vec<Light> {
    vec![
        Light::Directional {
            direction: [0.35, 0.75, -0.55],
            irradiance: [3.2, 3.1, 2.9],
        },
        Light::Environment {
            radiance: [0.1, 0.11, 0.13],
        },
    ]
}

/// Scene parameters shared by every technique.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RenderParams {
    /// Extinction per world unit at opacity 1.
    pub density_scale: f32,
    /// Henyey-Greenstein asymmetry in (−1, 1); 0 is isotropic.
    pub g: f32,
    /// Display exposure multiplier applied before the sRGB transfer (display only).
    pub exposure: f32,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            density_scale: 60.0,
            g: 0.0,
            exposure: 1.0,
        }
    }
}

/// Messages from a client to the server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ClientMessage {
    /// First message of a connection.
    Hello {
        protocol: u32,
        /// Join an existing session (the id from its `welcome`) instead of starting a new one.
        /// When joining, `viewport`, `dataset` and `technique` are ignored: the session's own
        /// state wins and arrives in `welcome` (a `viewport` or `technique_options` out of range
        /// is still refused).
        #[serde(default)]
        session: Option<String>,
        #[serde(default)]
        token: Option<String>,
        #[serde(default)]
        viewport: Option<Viewport>,
        /// Dataset to open; the server's default when absent.
        #[serde(default)]
        dataset: Option<String>,
        #[serde(default)]
        technique: Option<String>,
        /// Options of the techniques for the new session (as in the `technique` message).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        technique_options: Option<TechniqueOptions>,
        /// Display name shown to the other viewers with this viewer's edits.
        #[serde(default)]
        name: Option<String>,
        /// Flow control: at most this many frames (1..=`MAX_FRAMES_IN_FLIGHT`) are sent before
        /// the client acknowledges them with `ack`. Absent: no acknowledgements; TCP
        /// backpressure alone paces the frames.
        #[serde(default)]
        max_in_flight: Option<u32>,
    },
    /// Acknowledges every frame up to and including `seq` (with `max_in_flight`).
    Ack {
        seq: u64,
    },
    /// Changes this viewer's display name (as in `hello.name`).
    Name {
        name: String,
    },
    /// Open another dataset (by name, as listed by `/api/datasets`).
    Dataset {
        name: String,
    },
    Camera(Camera),
    Tf(TransferFunction),
    /// Replace all lights.
    Lights {
        lights: Vec<Light>,
    },
    /// Switch technique, and/or change technique options: the fields `options` sets replace
    /// the session's, the others keep their value.
    Technique {
        name: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        options: Option<TechniqueOptions>,
    },
    Viewport(Viewport),
    /// Change any of the render parameters; absent fields keep their value.
    Params {
        #[serde(default)]
        density_scale: Option<f32>,
        #[serde(default)]
        g: Option<f32>,
        #[serde(default)]
        exposure: Option<f32>,
    },
    /// Streaming quality for this viewer.
    Quality {
        /// JPEG quality (1–100) for frames sent while the picture changes.
        #[serde(default)]
        jpeg_quality: Option<u8>,
        /// Progressive iterations after which the picture counts as converged.
        #[serde(default)]
        iterations: Option<u32>,
    },
}

/// What the server knows about a dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetInfo {
    pub name: String,
    /// `dicom`, `nrrd`, `nifti`, `vti` or `phantom`.
    pub kind: String,
    /// Present once the dataset has been loaded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub details: Option<DatasetDetails>,
}

/// Properties known once a dataset is loaded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetDetails {
    pub dims: [u32; 3],
    /// Voxel spacing in the dataset's units (mm for medical images).
    pub spacing: [f32; 3],
    /// Original value range: normalized value v maps to `value_min + v·(value_max − value_min)`.
    pub value_min: f64,
    pub value_max: f64,
    /// `HU` for CT, empty when unknown.
    pub units: String,
    pub modality: String,
    pub format: String,
    /// World-space box size (longest side 1).
    pub world_extent: [f32; 3],
    /// 256 bins over the normalized value.
    pub histogram: Vec<u32>,
    pub warnings: Vec<String>,
    /// Present when the server renders a reduced copy because the volume does not fit the GPU
    /// (`dims` and `spacing` above are the reduced copy's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub downsampled: Option<Downsampled>,
}

/// How a volume too large for the GPU was reduced to fit.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Downsampled {
    /// Voxels averaged per axis (2: every 2×2×2 block became one voxel).
    pub factor: u32,
    /// The volume's dimensions as loaded.
    pub original_dims: [u32; 3],
    /// What it did not fit, e.g. `3D textures of at most 2048 per axis`.
    pub reason: String,
}

/// The rendering techniques, by the name the protocol uses for each (`hello.technique`, the
/// `technique` message, `welcome.techniques`). Messages carry the name as a string, so that an
/// unknown one is answered with `unknown_technique`; the server turns it into this enum, whose
/// matches are exhaustive: a new technique is added here and the compiler lists the rest.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TechniqueKind {
    Raymarch,
    Pathtrace,
    Manylight,
    Irradiance,
    Photon,
}

impl TechniqueKind {
    /// Every technique, in the order clients list them.
    pub const ALL: [TechniqueKind; 5] = [
        TechniqueKind::Raymarch,
        TechniqueKind::Pathtrace,
        TechniqueKind::Manylight,
        TechniqueKind::Irradiance,
        TechniqueKind::Photon,
    ];

    /// The protocol's name of the technique.
    pub fn name(self) -> &'static str {
        match self {
            TechniqueKind::Raymarch => "raymarch",
            TechniqueKind::Pathtrace => "pathtrace",
            TechniqueKind::Manylight => "manylight",
            TechniqueKind::Irradiance => "irradiance",
            TechniqueKind::Photon => "photon",
        }
    }

    /// The technique of a protocol name, if there is one.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }
}

/// A technique the server offers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TechniqueInfo {
    pub name: String,
    pub description: String,
    /// The technique's options with their default values (its group of `TechniqueOptions`;
    /// empty for a technique without options).
    #[serde(default, skip_serializing_if = "TechniqueOptions::is_empty")]
    pub default_options: TechniqueOptions,
}

/// One person (connection) viewing a session.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ViewerInfo {
    /// Unique within the session, stable for the connection.
    pub id: u32,
    pub name: String,
}

/// The full editable state of a session, as sent to a (late) joiner.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionState {
    pub dataset: String,
    pub technique: String,
    /// Options of every technique as set so far (absent fields: the technique's default).
    #[serde(default, skip_serializing_if = "TechniqueOptions::is_empty")]
    pub technique_options: TechniqueOptions,
    pub camera: Camera,
    pub tf: TransferFunction,
    pub lights: Vec<Light>,
    pub params: RenderParams,
    pub viewport: Viewport,
    pub iterations: u32,
    pub jpeg_quality: u8,
}

/// Codes in `error` messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// Not JSON, or not an object with a known `type`.
    BadMessage,
    /// A field is out of range or inconsistent.
    BadValue,
    /// The message is larger than [`MAX_MESSAGE_BYTES`].
    TooLarge,
    /// A message other than `hello` came first, or `hello` came twice.
    NotReady,
    /// More messages per second than the server accepts; the message was dropped.
    RateLimited,
    /// The client speaks another protocol version.
    ProtocolVersion,
    /// `hello` named a session that does not exist (any more).
    UnknownSession,
    /// The session already has `MAX_VIEWERS_PER_SESSION` viewers.
    SessionFull,
    UnknownDataset,
    UnknownTechnique,
    /// The dataset exists but could not be read.
    LoadFailed,
    /// The GPU cannot hold what was asked for.
    GpuMemory,
    /// The GPU failed or was lost.
    Gpu,
    Internal,
    /// This server holds as many sessions as it may (`--max-sessions`); try again later or
    /// on another server. Joining an existing session is still possible.
    AtCapacity,
    /// This server is draining for a restart or scale-down: it serves its sessions until they
    /// end but opens no new one; open it at the deployment's root (another server).
    Draining,
}

/// Messages from the server to a client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    Welcome {
        protocol: u32,
        session: String,
        server_version: String,
        /// The GPU adapter that renders, e.g. `llvmpipe (LLVM 15.0.6, 256 bits)`.
        adapter: String,
        /// `true` when the adapter is a CPU rasterizer (lavapipe/llvmpipe): a GPU was not found
        /// or not passed into the container, and frames will be slow.
        #[serde(default)]
        software_renderer: bool,
        dataset: DatasetInfo,
        techniques: Vec<TechniqueInfo>,
        state: SessionState,
        /// This connection, as the other viewers see it.
        viewer: ViewerInfo,
        /// Everyone viewing the session, this viewer included.
        viewers: Vec<ViewerInfo>,
        /// `true` when `hello` joined an existing session.
        joined: bool,
        /// The scene version `state` shows.
        version: u64,
        /// The path prefix that reaches this server process directly behind a router that
        /// spreads new sessions over several (e.g. `/p/3/`): viewers of this session, its
        /// share link and reconnects must use it. Absent when the server is reached directly.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        route: Option<String>,
    },
    /// A viewer changed the session (last writer wins). Sent to every viewer, the editor
    /// included, in the order the server applied the edits; `edit` is the client message
    /// as applied (`camera`, `tf`, `lights`, `technique`, `viewport`, `params`, or `quality`
    /// with `iterations` only). Dataset switches arrive as `dataset_loaded`.
    Edited {
        by: ViewerInfo,
        /// The scene version this edit produced; frames with `scene_version` ≥ it show it.
        version: u64,
        edit: Box<ClientMessage>,
    },
    /// The whole session state, sent when a viewer fell behind on `edited` messages (it
    /// replaces everything the viewer missed, including a dataset switch).
    State {
        state: SessionState,
        version: u64,
        dataset: DatasetInfo,
        viewers: Vec<ViewerInfo>,
    },
    /// Someone joined or left; the full list.
    Viewers {
        viewers: Vec<ViewerInfo>,
    },
    /// The session switched datasets (after a `dataset` message from any viewer).
    DatasetLoaded {
        dataset: DatasetInfo,
        state: SessionState,
        /// Who switched.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        by: Option<ViewerInfo>,
    },
    /// A dataset is arriving (a series fetched from a PACS, instance by instance): `done` of
    /// `total` parts are in. Sent before `welcome` to the viewer whose `hello` opens it, and to
    /// every viewer of a session switching to it; `dataset_loaded` or `welcome` follows.
    Loading {
        dataset: String,
        done: u32,
        total: u32,
    },
    /// Progress of the current picture, sent with frames at a modest rate.
    Stats(Stats),
    Error {
        code: ErrorCode,
        message: String,
    },
    /// The server is draining (a restart or scale-down): the session goes on for at most
    /// `seconds_left`, then `bye`; a viewer can reopen its view at the deployment's root.
    Draining {
        seconds_left: u64,
        message: String,
    },
    /// The server is going away.
    Bye {
        reason: String,
    },
}

/// Progress and cost of the current picture.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Stats {
    pub technique: String,
    pub iteration: u32,
    pub target_iterations: u32,
    pub converged: bool,
    /// GPU milliseconds of the last step (timestamp queries where available, else wall time).
    pub gpu_ms: f32,
    /// Per-session GPU memory in bytes.
    pub memory_bytes: u64,
    /// Frames sent per second to this viewer over the last second.
    pub fps: f32,
    /// Viewers of the session.
    #[serde(default)]
    pub viewers: u32,
    /// JPEG quality currently chosen for this viewer (adapted to its bandwidth).
    #[serde(default)]
    pub jpeg_quality: u8,
    /// Frames this viewer skipped because a newer one was ready before it could take it.
    #[serde(default)]
    pub frames_skipped: u64,
    /// What the technique reports beyond progress (absent fields do not apply to it).
    #[serde(default)]
    pub details: TechniqueDetails,
}

/// Technique-specific figures, in `stats` and frame metadata. Every field is optional.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TechniqueDetails {
    /// `photon`: photon paths traced since the session started (retraced ones included).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_traced: Option<u64>,
    /// `photon`: photon paths in the current map.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_in_map: Option<u64>,
    /// `photon`: share of the map's paths the last TF edit retraced, in percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub photons_retraced_pct: Option<f32>,
    /// `photon`: share of the view-ray segments the last TF edit gathered again, in percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub segments_recomputed_pct: Option<f32>,
    /// `manylight`: virtual lights in use.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub virtual_lights: Option<u32>,
    /// `manylight`: bytes of their adaptive volumetric shadow maps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shadow_map_bytes: Option<u64>,
    /// `manylight`: milliseconds the last tracing of the lights and map build took.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub build_ms: Option<f32>,
    /// `manylight`: share of the light paths the last TF edit traced again, in percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light_paths_retraced_pct: Option<f32>,
    /// `manylight`: share of the shadow maps the last TF edit built again, in percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shadow_maps_rebuilt_pct: Option<f32>,
    /// `irradiance`: entries in the irradiance cache.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_entries: Option<u32>,
    /// `irradiance`: references held by the cache's multi-reference octree.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub octree_references: Option<u64>,
    /// `irradiance`: share of first scattering events the cache answered recently (0–1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_hit_rate: Option<f32>,
    /// `irradiance`: entries being created.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pending_entries: Option<u32>,
    /// `irradiance`: whether the cache is used (false with an anisotropic phase function:
    /// the technique then renders plain Monte Carlo).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_active: Option<bool>,
    /// `irradiance`: share of the entries the last TF edit kept, in percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_entries_kept_pct: Option<f32>,
}

/// Image encodings of frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameFormat {
    Jpeg,
    Png,
}

/// JSON header of a binary frame message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameMeta {
    /// The session's frame number: increases with every picture the session renders, and
    /// is the same for every viewer. A viewer that was busy skips frames (gaps are normal).
    pub seq: u64,
    pub format: FrameFormat,
    pub width: u32,
    pub height: u32,
    pub technique: String,
    /// Progressive iterations accumulated in this picture.
    pub iteration: u32,
    pub target_iterations: u32,
    /// No further iterations will be rendered for this state.
    pub converged: bool,
    /// The image is lossless (PNG of the exact framebuffer).
    pub lossless: bool,
    /// JPEG quality when lossy.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quality: Option<u8>,
    /// Counter of scene edits applied to this picture; a client can match its own edits.
    pub scene_version: u64,
    /// An interactive preview (shown while edits stream in), not the technique's estimate:
    /// single scattering lit from a light volume, whatever the technique.
    #[serde(default)]
    pub preview: bool,
    /// Image size over the viewport's, per axis: 1, 0.5, 0.25 or 0.125 (the client scales the
    /// picture up to its canvas).
    #[serde(default = "full_scale")]
    pub resolution_scale: f32,
    /// A preview's brightness match to the technique's last still; absent for other frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preview_match: Option<PreviewMatch>,
    pub render_ms: f32,
    pub encode_ms: f32,
    /// Technique-specific figures (as in `stats`).
    #[serde(default)]
    pub details: TechniqueDetails,
}

/// How a preview's brightness was matched to the technique's still (docs/architecture.md,
/// "Interaction mode"): the preview is the environment seen through the volume, plus
/// `gain` × its single scattering, plus `multiple_weight` × its approximate multiple scattering
/// (GI techniques only), per RGB channel, fitted at the last rest.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PreviewMatch {
    pub gain: [f32; 3],
    pub multiple_weight: [f32; 3],
}

fn full_scale() -> f32 {
    1.0
}

/// A scene file for `voxlight render` (DESIGN.md "Fixed names"): the protocol's field names.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// `phantom:NAME` or a path to a volume file or DICOM folder.
    pub dataset: String,
    #[serde(default)]
    pub camera: Camera,
    /// Absent: the server's default for the dataset.
    #[serde(default)]
    pub tf: Option<TransferFunction>,
    #[serde(default = "default_lights")]
    pub lights: Vec<Light>,
    #[serde(default = "default_technique")]
    pub technique: String,
    /// Options of the techniques (as in the `technique` message's `options`).
    #[serde(default)]
    pub technique_options: TechniqueOptions,
    #[serde(default = "default_density_scale")]
    pub density_scale: f32,
    #[serde(default)]
    pub g: f32,
    #[serde(default = "default_exposure")]
    pub exposure: f32,
    #[serde(default = "default_width")]
    pub width: u32,
    #[serde(default = "default_width")]
    pub height: u32,
    /// Progressive iterations (samples per pixel) to accumulate.
    #[serde(default = "default_iterations")]
    pub iterations: u32,
    /// Seed of the counter-based random numbers.
    #[serde(default)]
    pub seed: u32,
}

fn default_technique() -> String {
    "raymarch".to_owned()
}
fn default_density_scale() -> f32 {
    RenderParams::default().density_scale
}
fn default_exposure() -> f32 {
    1.0
}
fn default_width() -> u32 {
    512
}
fn default_iterations() -> u32 {
    64
}

/// Splits a binary frame message into its metadata and image bytes.
pub fn split_frame(bytes: &[u8]) -> Option<(FrameMeta, &[u8])> {
    let len = u32::from_le_bytes(bytes.get(..4)?.try_into().ok()?) as usize;
    let meta = bytes.get(4..4usize.checked_add(len)?)?;
    let meta = serde_json::from_slice(meta).ok()?;
    Some((meta, &bytes[4 + len..]))
}

/// Builds a binary frame message from metadata and image bytes.
pub fn join_frame(meta: &FrameMeta, image: &[u8]) -> Vec<u8> {
    let json = serde_json::to_vec(meta).unwrap_or_default();
    let mut out = Vec::with_capacity(4 + json.len() + image.len());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(image);
    out
}

#[cfg(test)]
mod tests {

    #[test]
    fn technique_names_round_trip_and_match_serde() {
        for kind in TechniqueKind::ALL {
            assert_eq!(TechniqueKind::from_name(kind.name()), Some(kind));
            assert_eq!(
                serde_json::to_string(&kind).unwrap(),
                format!("\"{}\"", kind.name())
            );
        }
        assert_eq!(TechniqueKind::from_name("warp"), None);
    }
    use super::*;

    #[test]
    fn design_core_shapes_parse() {
        let hello: ClientMessage = serde_json::from_str(
            r#"{"type":"hello","protocol":1,"viewport":{"width":64,"height":48},"dataset":"phantom:sphere"}"#,
        )
        .unwrap();
        assert!(matches!(
            hello,
            ClientMessage::Hello {
                protocol: 1,
                viewport: Some(Viewport {
                    width: 64,
                    height: 48
                }),
                ..
            }
        ));
        let cam: ClientMessage = serde_json::from_str(
            r#"{"type":"camera","eye":[0,0,3],"target":[0,0,0],"up":[0,1,0],"fov_deg":40}"#,
        )
        .unwrap();
        assert!(matches!(
            cam,
            ClientMessage::Camera(Camera { fov_deg: 40.0, .. })
        ));
        let tf: ClientMessage = serde_json::from_str(
            r#"{"type":"tf","points":[{"value":0.5,"color":[1,0,0],"opacity":0.2}]}"#,
        )
        .unwrap();
        assert!(
            matches!(tf, ClientMessage::Tf(TransferFunction { ref points }) if points.len() == 1)
        );
        let vp: ClientMessage =
            serde_json::from_str(r#"{"type":"viewport","width":10,"height":20}"#).unwrap();
        assert_eq!(
            vp,
            ClientMessage::Viewport(Viewport {
                width: 10,
                height: 20
            })
        );
        let lights: ClientMessage = serde_json::from_str(
            r#"{"type":"lights","lights":[{"kind":"environment","radiance":[1,1,1]},{"kind":"point","position":[0,0,2],"intensity":[3,3,3]}]}"#,
        )
        .unwrap();
        assert!(matches!(lights, ClientMessage::Lights { ref lights } if lights.len() == 2));
    }

    #[test]
    fn frame_round_trip() {
        let meta = FrameMeta {
            seq: 7,
            format: FrameFormat::Png,
            width: 2,
            height: 3,
            technique: "raymarch".into(),
            iteration: 4,
            target_iterations: 8,
            converged: false,
            lossless: true,
            quality: None,
            scene_version: 1,
            preview: true,
            resolution_scale: 0.25,
            preview_match: Some(PreviewMatch {
                gain: [1.25, 1.0, 0.5],
                multiple_weight: [0.5, 0.0, 0.25],
            }),
            render_ms: 1.0,
            encode_ms: 2.0,
            details: TechniqueDetails {
                virtual_lights: Some(3),
                ..TechniqueDetails::default()
            },
        };
        let bytes = join_frame(&meta, b"image");
        let (back, image) = split_frame(&bytes).unwrap();
        assert_eq!(back, meta);
        assert_eq!(image, b"image");
        assert!(split_frame(&bytes[..3]).is_none());
        assert!(split_frame(&[255, 255, 255, 255, b'{']).is_none());
    }

    #[test]
    fn scene_defaults_and_unknown_fields() {
        let scene: Scene = serde_json::from_str(r#"{"dataset":"phantom:sphere"}"#).unwrap();
        assert_eq!(scene.technique, "raymarch");
        assert_eq!(scene.lights, default_lights());
        assert!(serde_json::from_str::<Scene>(r#"{"dataset":"x","colour":1}"#).is_err());
    }

    #[test]
    fn technique_options_travel_by_name() {
        let message: ClientMessage = serde_json::from_str(
            r#"{"type":"technique","name":"manylight","options":{"manylight":{"virtual_lights":1000,"transmittance":"ray_marched"}}}"#,
        )
        .unwrap();
        let ClientMessage::Technique { name, options } = &message else {
            panic!("not a technique message: {message:?}");
        };
        assert_eq!(name, "manylight");
        let options = options.expect("options");
        assert_eq!(options.manylight.virtual_lights, Some(1000));
        assert_eq!(
            options.manylight.transmittance,
            Some(Transmittance::RayMarched)
        );
        assert!(options.photon.is_empty() && options.irradiance.is_empty());
        // Unset options are not written back, so an echo names only what was set.
        let echoed = serde_json::to_string(&message).unwrap();
        assert_eq!(
            echoed,
            r#"{"type":"technique","name":"manylight","options":{"manylight":{"virtual_lights":1000,"transmittance":"ray_marched"}}}"#
        );
        let plain: ClientMessage =
            serde_json::from_str(r#"{"type":"technique","name":"raymarch"}"#).unwrap();
        assert_eq!(
            plain,
            ClientMessage::Technique {
                name: "raymarch".into(),
                options: None
            }
        );
        let typo = serde_json::from_str::<ClientMessage>(
            r#"{"type":"technique","name":"irradiance","options":{"irradiance":{"lock":"screen"}}}"#,
        );
        assert!(
            typo.unwrap_err()
                .to_string()
                .contains("unknown field `lock`")
        );
    }
}
