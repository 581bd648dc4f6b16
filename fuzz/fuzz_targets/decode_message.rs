//! Message decoding: `MessageView::new_checked` and `Message::decode` never panic, agree with
//! each other, and every datagram that decodes re-encodes to exactly the same bytes (the
//! wire format has one encoding per message), which decode again to an equal `Message`.

#![no_main]

use coap::msg::{Message, MessageView, Reaction};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let view = MessageView::new_checked(data);
    let decoded = Message::decode(data);
    match (view, decoded) {
        (Ok(view), Ok(msg)) => {
            // The view's accessors read only what new_checked checked.
            assert_eq!(view.ty(), msg.ty);
            assert_eq!(view.code(), msg.code);
            assert_eq!(view.message_id(), msg.message_id);
            assert_eq!(view.token(), msg.token);
            assert_eq!(view.payload(), &msg.payload[..]);
            assert!(
                view.options()
                    .map(|(number, value)| (number, value.to_vec()))
                    .eq(msg.options.iter().map(|o| (o.number, o.value.to_vec()))),
                "view and owned options differ"
            );

            let encoded = msg.encode();
            assert_eq!(encoded.len(), msg.encoded_len(), "encoded_len is not exact");
            assert_eq!(encoded, data, "re-encoding changed the datagram");
            let again = Message::decode(&encoded);
            assert_eq!(again.as_ref(), Ok(&msg), "round trip changed the message");
        }
        (Err(view_err), Err(err)) => {
            assert_eq!(view_err, err);
            // The reaction is defined for every error, and a Reset answers with the
            // datagram's own message ID.
            if let Reaction::Reset(mid) = Reaction::from(&err) {
                assert_eq!(err.header.map(|(_, m)| m), Some(mid));
            }
        }
        (view, decoded) => panic!(
            "view and decode disagree: {:?} vs {:?}",
            view.err(),
            decoded.err()
        ),
    }
});
