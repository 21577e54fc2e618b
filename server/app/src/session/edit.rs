//! A viewer's edits: checked (`validate_message`), then applied to the session under its lock.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use tokio::sync::oneshot;
use voxlight_engine::camera::CameraBasis;
use voxlight_engine::scene::{validate_lights, validate_params, validate_viewport};
use voxlight_engine::{Change, Scene};
use voxlight_protocol::{
    ClientMessage, ErrorCode, MAX_FRAMES_IN_FLIGHT, RenderParams, ServerMessage, ViewerInfo,
};

use crate::AppState;
use crate::hub::{SessionCore, SharedSession};
use crate::render_service::Command;
use crate::reply::Reply;

use super::{MAX_ITERATIONS, ViewerLink};

use super::join::{check_technique, check_viewport, load_dataset, loading_progress};

/// Every check of a client message that needs no session state: ranges, finite numbers,
/// list lengths. `handle_message` runs it before touching the session (so a refused message
/// has no effect at all), `open_or_join` before anything else; what depends on the session or
/// the GPU (the viewport's pixel budget, technique and dataset names) is checked where it is
/// used. A message it accepts carries no number out of its documented range.
pub fn validate_message(message: &ClientMessage) -> Result<(), Reply> {
    match message {
        ClientMessage::Hello {
            viewport,
            technique_options,
            max_in_flight,
            ..
        } => {
            if let Some(n) = max_in_flight
                && !(1..=MAX_FRAMES_IN_FLIGHT).contains(n)
            {
                return Err(Reply::bad(format!(
                    "max_in_flight must be in 1..={MAX_FRAMES_IN_FLIGHT}, got {n}"
                )));
            }
            // Checked when joining too, where they are not used: a value out of range is a
            // client bug either way.
            if let Some(viewport) = viewport {
                validate_viewport(viewport).map_err(Reply::bad)?;
            }
            match technique_options {
                Some(options) => {
                    voxlight_engine::techniques::validate_options(options).map_err(Reply::bad)
                }
                None => Ok(()),
            }
        }
        ClientMessage::Camera(camera) => CameraBasis::new(camera).map(|_| ()).map_err(Reply::bad),
        // An empty list would hide the volume without a word: a client that wants that sends
        // one point of opacity 0 (issue 22 counts an empty TF as malformed).
        ClientMessage::Tf(tf) if tf.points.is_empty() => Err(Reply::bad(
            "a transfer function needs at least one point (one point of opacity 0 makes the \
             volume transparent)",
        )),
        ClientMessage::Tf(tf) => voxlight_engine::tf::validate(tf).map_err(Reply::bad),
        ClientMessage::Lights { lights } => validate_lights(lights).map_err(Reply::bad),
        ClientMessage::Viewport(viewport) => validate_viewport(viewport).map_err(Reply::bad),
        ClientMessage::Params {
            density_scale,
            g,
            exposure,
        } => {
            // Each parameter has its own range: the given ones are checked beside defaults.
            let d = RenderParams::default();
            validate_params(&RenderParams {
                density_scale: density_scale.unwrap_or(d.density_scale),
                g: g.unwrap_or(d.g),
                exposure: exposure.unwrap_or(d.exposure),
            })
            .map_err(Reply::bad)
        }
        ClientMessage::Quality {
            jpeg_quality,
            iterations,
        } => {
            if let Some(q) = jpeg_quality
                && !(1..=100).contains(q)
            {
                return Err(Reply::bad(format!(
                    "jpeg_quality must be in 1..=100, got {q}"
                )));
            }
            if let Some(n) = iterations
                && !(1..=MAX_ITERATIONS).contains(n)
            {
                return Err(Reply::bad(format!(
                    "iterations must be in 1..={MAX_ITERATIONS}, got {n}"
                )));
            }
            Ok(())
        }
        ClientMessage::Technique {
            options: Some(options),
            ..
        } => voxlight_engine::techniques::validate_options(options).map_err(Reply::bad),
        ClientMessage::Technique { options: None, .. }
        | ClientMessage::Ack { .. }
        | ClientMessage::Name { .. }
        | ClientMessage::Dataset { .. } => Ok(()),
    }
}

/// Applies one message. Session edits happen under the session lock, so every viewer sees
/// them in the order they were applied (last writer wins).
pub(super) async fn handle_message(
    state: &Arc<AppState>,
    session: &SharedSession,
    viewer: &mut ViewerInfo,
    message: ClientMessage,
    link: &ViewerLink,
) -> Result<(), Reply> {
    let arrived = Instant::now();
    match message {
        ClientMessage::Hello { .. } => {
            return Err(Reply::new(
                ErrorCode::NotReady,
                "this connection already said hello",
            ));
        }
        ClientMessage::Name { name } => {
            if let Some(renamed) = session.rename_viewer(viewer.id, &name) {
                *viewer = renamed;
                session.publish(ServerMessage::Viewers {
                    viewers: session.viewers(),
                });
            }
            return Ok(());
        }
        ClientMessage::Ack { seq } => {
            link.acked.send_if_modified(|acked| {
                let newer = seq > *acked;
                if newer {
                    *acked = seq;
                }
                newer
            });
            return Ok(());
        }
        _ => {}
    }
    validate_message(&message)?;
    // What depends on this GPU or only on this viewer, before the session is touched.
    match &message {
        ClientMessage::Viewport(viewport) => check_viewport(state, viewport)?,
        ClientMessage::Quality {
            jpeg_quality: Some(q),
            ..
        } => link.jpeg_quality.store(*q, Ordering::Relaxed),
        _ => {}
    }
    let mut core = session.core.lock().await;
    let mut scene = core.scene.clone();
    match message {
        ClientMessage::Technique { name, options } => {
            check_technique(state, &name)?;
            if let Some(options) = &options {
                scene.technique_options = scene.technique_options.overlaid(options);
                voxlight_engine::techniques::validate_options(&scene.technique_options)
                    .map_err(Reply::bad)?;
            }
            rebuild(
                state,
                session,
                &mut core,
                None,
                name.clone(),
                scene,
                arrived,
            )
            .await?;
            core.technique = name.clone();
            session.publish(ServerMessage::Edited {
                by: viewer.clone(),
                version: core.version,
                edit: Box::new(ClientMessage::Technique { name, options }),
            });
        }
        ClientMessage::Dataset { name } => {
            let events = session.events.clone();
            let progress = loading_progress(&name, move |message| {
                let _ = events.send(Arc::new(message));
            });
            let volume = load_dataset(state, &name, progress).await?;
            // A new dataset is a new scene: its own default TF and lights.
            scene.tf = crate::datasets::default_tf(&volume);
            scene.lights = crate::datasets::default_lights_for(&volume);
            let technique = core.technique.clone();
            let volume = Some(volume);
            rebuild(state, session, &mut core, volume, technique, scene, arrived).await?;
            core.dataset = name.clone();
            let dataset = state
                .catalog
                .info(&name)
                .ok_or_else(|| Reply::new(ErrorCode::Internal, "dataset vanished"))?;
            session.publish(ServerMessage::DatasetLoaded {
                dataset,
                state: core.state(link.jpeg_quality.load(Ordering::Relaxed)),
                by: Some(viewer.clone()),
            });
        }
        message => {
            let Some((change, edit)) = apply(message, &mut scene)? else {
                return Ok(());
            };
            core.scene = scene.clone();
            bump_version(session, &mut core, arrived);
            state
                .render
                .send(Command::Edit {
                    id: session.render_id,
                    scene,
                    change,
                    version: core.version,
                })
                .await
                .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
            session.publish(ServerMessage::Edited {
                by: viewer.clone(),
                version: core.version,
                edit: Box::new(edit),
            });
        }
    }
    Ok(())
}

/// Applies a scene edit (a message [`validate_message`] accepted) to `scene`: what it changes
/// for the renderer and the message every viewer is told. `Ok(None)`: nothing to render again
/// (the viewport the scene has, a `quality` without `iterations`). A refused message leaves
/// `scene` as it was. Messages that are not scene edits (`hello`, `ack`, `name`, `technique`,
/// `dataset`: they need the session or the GPU) are refused.
pub fn apply(
    message: ClientMessage,
    scene: &mut Scene,
) -> Result<Option<(Change, ClientMessage)>, Reply> {
    Ok(Some(match message {
        ClientMessage::Camera(camera) => {
            scene.camera = camera;
            (Change::Camera, ClientMessage::Camera(camera))
        }
        ClientMessage::Tf(tf) => {
            let change = Change::tf(&scene.tf, &tf);
            scene.tf = tf.clone();
            (change, ClientMessage::Tf(tf))
        }
        ClientMessage::Lights { lights } => {
            scene.lights = lights.clone();
            (Change::Lights, ClientMessage::Lights { lights })
        }
        ClientMessage::Viewport(viewport) => {
            if viewport == scene.viewport {
                return Ok(None);
            }
            scene.viewport = viewport;
            (Change::Viewport, ClientMessage::Viewport(viewport))
        }
        ClientMessage::Params {
            density_scale,
            g,
            exposure,
        } => {
            let params = RenderParams {
                density_scale: density_scale.unwrap_or(scene.params.density_scale),
                g: g.unwrap_or(scene.params.g),
                exposure: exposure.unwrap_or(scene.params.exposure),
            };
            validate_params(&params).map_err(Reply::bad)?;
            scene.params = params;
            let edit = ClientMessage::Params {
                density_scale: Some(params.density_scale),
                g: Some(params.g),
                exposure: Some(params.exposure),
            };
            (Change::Params, edit)
        }
        ClientMessage::Quality { iterations, .. } => {
            let Some(n) = iterations else {
                return Ok(None);
            };
            scene.target_iterations = n;
            let edit = ClientMessage::Quality {
                jpeg_quality: None,
                iterations: Some(n),
            };
            (Change::Iterations, edit)
        }
        ClientMessage::Hello { .. }
        | ClientMessage::Ack { .. }
        | ClientMessage::Name { .. }
        | ClientMessage::Technique { .. }
        | ClientMessage::Dataset { .. } => {
            return Err(Reply::new(
                ErrorCode::Internal,
                "not a scene edit: handled with the session",
            ));
        }
    }))
}

/// Counts an edit: the next scene version, remembered with its arrival time unless an older
/// edit is still waiting for its frame.
fn bump_version(session: &SharedSession, core: &mut SessionCore, arrived: Instant) {
    core.version += 1;
    if let Ok(mut pending) = session.edit_clock.lock() {
        pending.get_or_insert((core.version, arrived));
    }
}

/// Swaps the session's volume and/or technique on the render thread; the version advances
/// only when that worked.
async fn rebuild(
    state: &Arc<AppState>,
    session: &SharedSession,
    core: &mut SessionCore,
    volume: Option<Arc<voxlight_volumes::Volume>>,
    technique: String,
    scene: Scene,
    arrived: Instant,
) -> Result<(), Reply> {
    let (reply, done) = oneshot::channel();
    state
        .render
        .send(Command::Rebuild {
            id: session.render_id,
            volume,
            technique,
            scene: scene.clone(),
            version: core.version + 1,
            reply,
        })
        .await
        .map_err(|e| Reply::new(ErrorCode::Gpu, e.to_string()))?;
    done.await
        .map_err(|_| Reply::new(ErrorCode::Internal, "render thread dropped the request"))?
        .map_err(|e| Reply::new(crate::render_service::error_code(&e), e.to_string()))?;
    core.scene = scene;
    bump_version(session, core, arrived);
    Ok(())
}

#[cfg(test)]
mod tests {
    use voxlight_protocol::{Camera, Light, TfPoint, TransferFunction, Viewport};

    use super::*;

    fn scene() -> Scene {
        Scene::default()
    }

    #[test]
    fn a_camera_edit_moves_the_camera_and_is_echoed() {
        let mut s = scene();
        let camera = Camera {
            fov_deg: 45.0,
            ..s.camera
        };
        let (change, echo) = apply(ClientMessage::Camera(camera), &mut s)
            .expect("accepted")
            .expect("an edit");
        assert_eq!(change, Change::Camera);
        assert_eq!(s.camera, camera);
        assert!(matches!(echo, ClientMessage::Camera(c) if c == camera));
    }

    #[test]
    fn a_tf_edit_is_classified_against_the_scene_before_it() {
        let mut s = scene();
        let before = s.tf.clone();
        let after = TransferFunction {
            points: vec![
                TfPoint {
                    value: 0.2,
                    color: [1.0, 0.5, 0.2],
                    opacity: 0.0,
                },
                TfPoint {
                    value: 0.8,
                    color: [1.0, 1.0, 1.0],
                    opacity: 0.7,
                },
            ],
        };
        assert_ne!(before, after);
        let (change, _) = apply(ClientMessage::Tf(after.clone()), &mut s)
            .expect("accepted")
            .expect("an edit");
        let Change::Tf { old, .. } = &change else {
            panic!("a TF change: {change:?}")
        };
        assert_eq!(old, &before);
        assert_eq!(change, Change::tf(&before, &after));
        assert_eq!(s.tf, after);
    }

    #[test]
    fn the_viewport_the_scene_has_changes_nothing() {
        let mut s = scene();
        let same = s.viewport;
        assert!(
            apply(ClientMessage::Viewport(same), &mut s)
                .expect("accepted")
                .is_none()
        );
        let wider = Viewport {
            width: same.width + 16,
            ..same
        };
        let (change, _) = apply(ClientMessage::Viewport(wider), &mut s)
            .expect("accepted")
            .expect("an edit");
        assert_eq!(change, Change::Viewport);
        assert_eq!(s.viewport, wider);
    }

    #[test]
    fn params_given_in_part_keep_the_rest_and_echo_all() {
        let mut s = scene();
        let before = s.params;
        let message = ClientMessage::Params {
            density_scale: None,
            g: Some(0.5),
            exposure: None,
        };
        let (change, echo) = apply(message, &mut s).expect("accepted").expect("an edit");
        assert_eq!(change, Change::Params);
        assert_eq!(s.params.g, 0.5);
        assert_eq!(s.params.density_scale, before.density_scale);
        assert!(matches!(
            echo,
            ClientMessage::Params { density_scale: Some(d), g: Some(g), exposure: Some(_) }
                if d == before.density_scale && g == 0.5
        ));
    }

    #[test]
    fn a_refused_edit_leaves_the_scene_as_it_was() {
        let mut s = scene();
        let before = s.clone();
        let message = ClientMessage::Params {
            density_scale: Some(2.0),
            g: Some(1.5),
            exposure: None,
        };
        let reply = apply(message, &mut s).expect_err("g out of range");
        assert_eq!(reply.code, ErrorCode::BadValue);
        assert_eq!(s, before);
    }

    #[test]
    fn quality_without_iterations_renders_nothing_again() {
        let mut s = scene();
        let only_jpeg = ClientMessage::Quality {
            jpeg_quality: Some(50),
            iterations: None,
        };
        assert!(apply(only_jpeg, &mut s).expect("accepted").is_none());
        let more = ClientMessage::Quality {
            jpeg_quality: Some(50),
            iterations: Some(512),
        };
        let (change, echo) = apply(more, &mut s).expect("accepted").expect("an edit");
        assert_eq!(change, Change::Iterations);
        assert_eq!(s.target_iterations, 512);
        // The JPEG quality is the viewer's own: not told to the others.
        assert!(matches!(
            echo,
            ClientMessage::Quality {
                jpeg_quality: None,
                iterations: Some(512)
            }
        ));
    }

    #[test]
    fn lights_are_replaced_whole() {
        let mut s = scene();
        let lights: Vec<Light> = Vec::new();
        let (change, _) = apply(ClientMessage::Lights { lights }, &mut s)
            .expect("accepted")
            .expect("an edit");
        assert_eq!(change, Change::Lights);
        assert!(s.lights.is_empty());
    }

    #[test]
    fn an_empty_tf_is_refused_one_transparent_point_is_not() {
        let empty = ClientMessage::Tf(TransferFunction { points: vec![] });
        let reply = validate_message(&empty).expect_err("empty TF");
        assert_eq!(reply.code, ErrorCode::BadValue);
        let transparent = ClientMessage::Tf(TransferFunction {
            points: vec![TfPoint {
                value: 0.5,
                color: [1.0; 3],
                opacity: 0.0,
            }],
        });
        assert!(validate_message(&transparent).is_ok());
    }

    #[test]
    fn messages_that_need_the_session_are_not_scene_edits() {
        let mut s = scene();
        let before = s.clone();
        for message in [
            ClientMessage::Ack { seq: 3 },
            ClientMessage::Name { name: "x".into() },
            ClientMessage::Dataset {
                name: "bonsai".into(),
            },
        ] {
            assert!(apply(message, &mut s).is_err());
        }
        assert_eq!(s, before);
    }
}
