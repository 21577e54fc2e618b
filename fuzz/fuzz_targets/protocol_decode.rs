//! Client messages: any bytes through the server's decode (`serde_json` into `ClientMessage`)
//! and its stateless validation (`session::validate_message`: camera, TF, lights, viewport,
//! params, quality, technique options), as `session.rs` runs them. A message that passes must
//! survive the server's echo (`edited`) to other viewers: serialize, parse, equal. Server
//! messages are decoded too (what a client library parses).

#![no_main]

use libfuzzer_sys::fuzz_target;
use voxlight_protocol::{ClientMessage, MAX_MESSAGE_BYTES, ServerMessage};
use voxlight_app::session::validate_message;

fuzz_target!(|data: &[u8]| {
    if data.len() > MAX_MESSAGE_BYTES {
        return;
    }
    if let Ok(message) = serde_json::from_slice::<ClientMessage>(data)
        && validate_message(&message).is_ok()
    {
        if let ClientMessage::Tf(tf) = &message {
            // What an accepted TF edit computes before rendering.
            let lut = voxlight_engine::tf::bake(tf);
            assert!(lut.iter().flatten().all(|x| x.is_finite()));
            let _ = voxlight_engine::tf::query_historygram(&Default::default(), tf);
        }
        let echo = serde_json::to_string(&message).expect("an accepted message serializes");
        let back: ClientMessage =
            serde_json::from_str(&echo).expect("the echo of an accepted message parses");
        assert_eq!(back, message, "echo changed the message: {echo}");
    }
    let _ = serde_json::from_slice::<ServerMessage>(data);
});
