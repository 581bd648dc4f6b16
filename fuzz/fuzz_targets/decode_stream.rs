//! Stream framing (RFC 8323): `stream::decode` and `stream::decode_ws` never panic on any
//! bytes; every frame that decodes re-encodes to exactly the bytes it came from (each
//! framing has one encoding per frame) and decodes again to an equal frame; a buffer cut
//! inside a frame asks for no more bytes than the frame lacks; a signalling frame that
//! reads as a `Signal` writes back to a frame that reads as the same `Signal`.

#![no_main]

use coap::msg::signal::Signal;
use coap::msg::stream::{self, Decoded, Frame};
use libfuzzer_sys::fuzz_target;

/// The limit the target decodes under: small enough that a header announcing more is
/// refused, large enough for every input libFuzzer makes by default.
const MAX: usize = 1 << 16;

fn check_signal(frame: &Frame) {
    if let Ok(signal) = Signal::decode(frame) {
        let again = signal.to_frame(frame.token, frame.payload.clone());
        assert_eq!(Signal::decode(&again).as_ref(), Ok(&signal), "signal round trip");
    }
}

fuzz_target!(|data: &[u8]| {
    // A buffer may hold several frames: walk them as a connection would.
    let mut rest = data;
    while let Ok(Decoded::Frame { frame, consumed }) = stream::decode(rest, MAX) {
        assert!(consumed > 0 && consumed <= rest.len());
        let encoded = frame.encode();
        assert_eq!(encoded.len(), frame.encoded_len(), "encoded_len is not exact");
        assert_eq!(&encoded[..], &rest[..consumed], "re-encoding changed the frame");
        assert_eq!(
            stream::decode(&encoded, MAX),
            Ok(Decoded::Frame { frame: frame.clone(), consumed }),
            "round trip changed the frame"
        );
        if let Ok(Decoded::Incomplete { needed }) = stream::decode(&rest[..consumed - 1], MAX) {
            assert!(needed >= 1 && needed <= consumed, "asks for {needed} of {consumed}");
        } else {
            panic!("a frame cut short is not incomplete");
        }
        check_signal(&frame);
        rest = &rest[consumed..];
    }

    if let Ok(frame) = stream::decode_ws(data, MAX) {
        assert_eq!(frame.encode_ws(), data, "re-encoding changed the WebSocket message");
        assert_eq!(frame.ws_encoded_len(), data.len());
        check_signal(&frame);
    }
});
