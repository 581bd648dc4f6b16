//! The stream framing and the signalling messages against RFC 8323: byte vectors worked
//! out by hand from §3.2 (each length class and its edges), §4.2 (WebSockets) and §5
//! (CSM, Ping, Release, Abort), partial buffers, the size limit, and proptest round trips.

use bytes::Bytes;
use coap::msg::signal::{Abort, Csm, Release, Signal, SignalError};
use coap::msg::stream::{self, Decoded, Frame, FrameError};
use coap::msg::{DecodeErrorKind, Message};
use coap::{Code, OptionNumber, Options, Token, Type};
use proptest::prelude::*;

/// Generous enough for every vector below.
const MAX: usize = 1 << 20;

fn frame(code: Code, token: &[u8], options: &[(u16, &[u8])], payload: &[u8]) -> Frame {
    let mut opts = Options::new();
    for (number, value) in options {
        opts.push(OptionNumber(*number), value);
    }
    Frame {
        code,
        token: Token::new(token).unwrap(),
        options: opts,
        payload: Bytes::copy_from_slice(payload),
    }
}

/// `bytes` is exactly `expected` over TCP: it encodes to them, `encoded_len` is exact, and
/// they decode back, with bytes after the frame left alone.
#[track_caller]
fn assert_tcp(expected: &Frame, bytes: &[u8]) {
    assert_eq!(expected.encode(), bytes);
    assert_eq!(expected.encoded_len(), bytes.len());
    let mut more = bytes.to_vec();
    more.extend_from_slice(&[0x00, 0xe1]);
    assert_eq!(
        stream::decode(&more, MAX),
        Ok(Decoded::Frame {
            frame: expected.clone(),
            consumed: bytes.len()
        })
    );
}

#[track_caller]
fn assert_malformed(bytes: &[u8], kind: DecodeErrorKind, offset: usize) {
    assert_eq!(
        stream::decode(bytes, MAX),
        Err(FrameError::Malformed { kind, offset }),
        "{bytes:02x?}"
    );
}

fn cat(parts: &[&[u8]]) -> Vec<u8> {
    parts.concat()
}

// ------------------------------------------------------------------ §3.2 length classes

#[test]
fn rfc8323_3_2_len_0_to_12_is_the_length_itself() {
    // GET, token 0xab, Uri-Path "a" (delta 11, length 1): 2 bytes after the token.
    let get = frame(Code::GET, &[0xab], &[(11, b"a")], b"");
    assert_tcp(&get, &[0x21, 0x01, 0xab, 0xb1, b'a']);
    // Nothing after the code: Len 0.
    assert_tcp(&frame(Code::CSM, &[], &[], b""), &[0x00, 0xe1]);
    // 11 payload bytes and the marker: Len 12, the largest without an extension.
    let content = frame(Code::CONTENT, &[], &[], &[7; 11]);
    assert_tcp(&content, &cat(&[&[0xc0, 0x45, 0xff], &[7; 11]]));
}

#[test]
fn rfc8323_3_2_len_13_adds_one_byte_of_length_minus_13() {
    let smallest = frame(Code::CONTENT, &[], &[], &[7; 12]);
    assert_tcp(&smallest, &cat(&[&[0xd0, 0x00, 0x45, 0xff], &[7; 12]]));
    let largest = frame(Code::CONTENT, &[1, 2], &[], &[7; 267]);
    assert_tcp(
        &largest,
        &cat(&[&[0xd2, 0xff, 0x45, 1, 2, 0xff], &[7; 267]]),
    );
}

#[test]
fn rfc8323_3_2_len_14_adds_two_bytes_of_length_minus_269() {
    let smallest = frame(Code::CONTENT, &[], &[], &[7; 268]);
    assert_tcp(
        &smallest,
        &cat(&[&[0xe0, 0x00, 0x00, 0x45, 0xff], &[7; 268]]),
    );
    let largest = frame(Code::CONTENT, &[], &[], &[7; 65803]);
    assert_tcp(
        &largest,
        &cat(&[&[0xe0, 0xff, 0xff, 0x45, 0xff], &[7; 65803]]),
    );
}

#[test]
fn rfc8323_3_2_len_15_adds_four_bytes_of_length_minus_65805() {
    let smallest = frame(Code::CONTENT, &[], &[], &[7; 65804]);
    assert_tcp(
        &smallest,
        &cat(&[&[0xf0, 0, 0, 0, 0, 0x45, 0xff], &[7; 65804]]),
    );
    let bigger = frame(Code::CONTENT, &[9], &[], &[7; 65804 + 0x0102]);
    assert_tcp(
        &bigger,
        &cat(&[
            &[0xf1, 0, 0, 0x01, 0x02, 0x45, 9, 0xff],
            &[7; 65804 + 0x0102],
        ]),
    );
}

#[test]
fn a_datagram_message_and_its_frame_carry_the_same_options() {
    let mut options = Options::new();
    options.set_path("/cams/pointclouds");
    options.set_uint(OptionNumber::ACCEPT, 60);
    let msg = Message {
        ty: Type::Con,
        code: Code::GET,
        message_id: 0x1234,
        token: Token::new(&[1, 2, 3]).unwrap(),
        options,
        payload: Bytes::new(),
    };
    let datagram = msg.encode();
    let f = Frame::from(msg.clone());
    let bytes = f.encode();
    // The same token, options and payload after the two headers: 4 bytes for the
    // datagram; for the frame Len 13 (19 bytes of options), its extension and the code.
    let head = bytes.len() - (datagram.len() - 4);
    assert_eq!(head, 3);
    assert_eq!(&bytes[head..], &datagram[4..]);
    assert_eq!(f.into_message(Type::Con, 0x1234), msg);
}

// ------------------------------------------------------------------ partial buffers, limits

#[test]
fn a_partial_frame_asks_for_the_bytes_it_still_needs() {
    let f = frame(Code::CONTENT, &[0xaa, 0xbb], &[], &[7; 12]);
    let bytes = f.encode();
    assert_eq!(bytes.len(), 1 + 1 + 1 + 2 + 13);
    assert_eq!(
        stream::decode(&[], MAX),
        Ok(Decoded::Incomplete { needed: 1 })
    );
    // The first byte promises one length byte, the code and two token bytes.
    assert_eq!(
        stream::decode(&bytes[..1], MAX),
        Ok(Decoded::Incomplete { needed: 4 })
    );
    // From the second byte on, the frame's length is known exactly.
    for have in 2..bytes.len() {
        assert_eq!(
            stream::decode(&bytes[..have], MAX),
            Ok(Decoded::Incomplete {
                needed: bytes.len() - have
            }),
            "{have} bytes"
        );
    }
    // A four-byte extension, two of it present: the rest of it and the code.
    assert_eq!(
        stream::decode(&[0xf0, 0, 0], MAX),
        Ok(Decoded::Incomplete { needed: 3 })
    );
}

#[test]
fn a_buffer_of_frames_decodes_one_at_a_time() {
    let csm = frame(Code::CSM, &[], &[(2, &[0x04, 0x80])], b"");
    let get = frame(Code::GET, &[5], &[(11, b"cams")], b"");
    let mut buf = csm.encode();
    buf.extend_from_slice(&get.encode());
    let mut got = Vec::new();
    let mut at = 0;
    while let Ok(Decoded::Frame { frame, consumed }) = stream::decode(&buf[at..], MAX) {
        got.push(frame);
        at += consumed;
    }
    assert_eq!(at, buf.len());
    assert_eq!(got, [csm, get]);
}

#[test]
fn an_oversize_frame_is_refused_from_its_header() {
    // Only the header has arrived; it announces 4 GiB.
    assert_eq!(
        stream::decode(&[0xf0, 0xff, 0xff, 0xff, 0xff], 1152),
        Err(FrameError::TooLarge {
            size: 4_295_033_106,
            max: 1152
        })
    );
    // The limit counts the whole frame: Len and TKL, the extension, the code, the token
    // and 21 bytes of marker and payload, 25 bytes.
    let f = frame(Code::CONTENT, &[1], &[], &[7; 20]);
    let bytes = f.encode();
    assert_eq!(bytes.len(), 25);
    assert!(matches!(
        stream::decode(&bytes, 25),
        Ok(Decoded::Frame { consumed: 25, .. })
    ));
    assert_eq!(
        stream::decode(&bytes[..3], 24),
        Err(FrameError::TooLarge { size: 25, max: 24 })
    );
    assert_eq!(
        stream::decode_ws(&f.encode_ws(), f.ws_encoded_len() - 1),
        Err(FrameError::TooLarge {
            size: f.ws_encoded_len() as u64,
            max: f.ws_encoded_len() - 1
        })
    );
}

#[test]
fn malformed_frames_are_refused_where_they_go_wrong() {
    // TKL 9: extended tokens (RFC 8974) are not supported.
    assert_malformed(&[0x09, 0x01], DecodeErrorKind::TokenLength, 0);
    // Code classes 1 and 6 are reserved; class 7 is signalling.
    assert_malformed(&[0x00, 0x20], DecodeErrorKind::ReservedClass, 1);
    assert_malformed(&[0x00, 0xc0], DecodeErrorKind::ReservedClass, 1);
    // A payload marker with nothing after it.
    assert_malformed(&[0x10, 0x45, 0xff], DecodeErrorKind::EmptyPayload, 2);
    // An option whose value runs past the length the header gave.
    assert_malformed(&[0x10, 0x01, 0xb1], DecodeErrorKind::Truncated, 2);
    // Option delta nibble 15 that is not a payload marker.
    assert_malformed(&[0x10, 0x01, 0xf0], DecodeErrorKind::ReservedNibble, 2);
}

// ------------------------------------------------------------------ §4.2 WebSockets

#[test]
fn rfc8323_4_2_websocket_messages_have_len_0_and_no_extension() {
    let csm = frame(Code::CSM, &[], &[(2, &[0x04, 0x80]), (4, b"")], b"");
    let ws = [0x00, 0xe1, 0x22, 0x04, 0x80, 0x20];
    assert_eq!(csm.encode_ws(), ws);
    assert_eq!(csm.ws_encoded_len(), ws.len());
    assert_eq!(stream::decode_ws(&ws, MAX), Ok(csm.clone()));
    // Over TCP the same message says its length, 4.
    assert_eq!(csm.encode(), [0x40, 0xe1, 0x22, 0x04, 0x80, 0x20]);
    // A long payload still has no extended length.
    let long = frame(Code::CONTENT, &[3], &[], &[7; 300]);
    let bytes = long.encode_ws();
    assert_eq!(&bytes[..4], &[0x01, 0x45, 3, 0xff]);
    assert_eq!(stream::decode_ws(&bytes, MAX), Ok(long));

    assert_eq!(
        stream::decode_ws(&[0x40, 0xe1, 0x22, 0x04, 0x80, 0x20], MAX),
        Err(FrameError::WebSocketLength(4))
    );
    for short in [&[][..], &[0x00], &[0x02, 0x45, 1]] {
        assert!(matches!(
            stream::decode_ws(short, MAX),
            Err(FrameError::Malformed {
                kind: DecodeErrorKind::Truncated,
                ..
            })
        ));
    }
}

// ------------------------------------------------------------------ §5 signalling

#[test]
fn rfc8323_5_3_an_empty_csm_keeps_the_defaults() {
    let Ok(Decoded::Frame { frame, .. }) = stream::decode(&[0x00, 0xe1], MAX) else {
        panic!("an empty CSM decodes");
    };
    let signal = Signal::decode(&frame).unwrap();
    assert_eq!(signal, Signal::Csm(Csm::default()));
    let Signal::Csm(csm) = signal else { panic!() };
    assert_eq!(csm.max_message_size_or_default(), 1152);
    assert_eq!(
        signal.to_frame(Token::EMPTY, Bytes::new()).encode(),
        [0x00, 0xe1]
    );
}

#[test]
fn rfc8323_5_3_a_csm_with_max_message_size_and_block_wise_transfer() {
    // Max-Message-Size (2) 1152 = 0x0480 in two bytes, then Block-Wise-Transfer (4, delta
    // 2), empty: 4 bytes of options.
    let bytes = [0x40, 0xe1, 0x22, 0x04, 0x80, 0x20];
    let csm = Signal::Csm(Csm {
        max_message_size: Some(1152),
        block_wise_transfer: true,
    });
    assert_tcp(&csm.to_frame(Token::EMPTY, Bytes::new()), &bytes);
    let Ok(Decoded::Frame { frame, .. }) = stream::decode(&bytes, MAX) else {
        panic!("the CSM decodes");
    };
    assert_eq!(Signal::decode(&frame), Ok(csm));
}

#[test]
fn rfc8323_5_4_a_ping_with_custody_and_its_pong() {
    // Token 0x42; Custody (2), empty.
    let bytes = [0x11, 0xe2, 0x42, 0x20];
    let ping = Signal::Ping { custody: true };
    let token = Token::new(&[0x42]).unwrap();
    assert_tcp(&ping.to_frame(token, Bytes::new()), &bytes);
    let Ok(Decoded::Frame { frame, .. }) = stream::decode(&bytes, MAX) else {
        panic!("the Ping decodes");
    };
    assert_eq!(Signal::decode(&frame), Ok(ping));
    assert_eq!(frame.token, token);
    let pong = Signal::Pong { custody: false }.to_frame(token, Bytes::new());
    assert_eq!(pong.encode(), [0x01, 0xe3, 0x42]);
}

#[test]
fn rfc8323_5_5_a_release_with_an_alternative_address_and_hold_off() {
    // Alternative-Address (2), 12 bytes: 0x2c; Hold-Off (4, delta 2) 60 s in one byte:
    // 0x21 0x3c. 15 bytes of options: Len 13, extension 2.
    let bytes = cat(&[&[0xd0, 0x02, 0xe4, 0x2c], b"coap+tcp://h", &[0x21, 0x3c]]);
    let release = Signal::Release(Release {
        alternative_addresses: vec!["coap+tcp://h".to_owned()],
        hold_off_s: Some(60),
    });
    assert_tcp(&release.to_frame(Token::EMPTY, Bytes::new()), &bytes);
    let f = release.to_frame(Token::EMPTY, Bytes::new());
    assert_eq!(Signal::decode(&f), Ok(release));
}

#[test]
fn rfc8323_5_6_an_abort_with_bad_csm_option_and_a_diagnostic() {
    // Bad-CSM-Option (2) 9 in one byte, then the payload marker and "bad": Len 6.
    let bytes = [0x60, 0xe5, 0x21, 0x09, 0xff, b'b', b'a', b'd'];
    let abort = Signal::Abort(Abort {
        bad_csm_option: Some(OptionNumber(9)),
    });
    assert_tcp(
        &abort.to_frame(Token::EMPTY, Bytes::from_static(b"bad")),
        &bytes,
    );
    let Ok(Decoded::Frame { frame, .. }) = stream::decode(&bytes, MAX) else {
        panic!("the Abort decodes");
    };
    assert_eq!(Signal::decode(&frame), Ok(abort));
    assert_eq!(&frame.payload[..], b"bad");
}

#[test]
fn rfc8323_5_2_option_numbers_are_per_signalling_code() {
    // Number 2 with the value 0x04 0x80: in a CSM, Max-Message-Size 1152; in a Ping,
    // Custody, which must be empty (so ignored); in an Abort, Bad-CSM-Option 1152; in a
    // Release, an Alternative-Address that is not UTF-8 (so ignored).
    let value: &[u8] = &[0x04, 0x80];
    let with = |code| frame(code, &[], &[(2, value)], b"");
    assert_eq!(
        Signal::decode(&with(Code::CSM)),
        Ok(Signal::Csm(Csm {
            max_message_size: Some(1152),
            block_wise_transfer: false
        }))
    );
    assert_eq!(
        Signal::decode(&with(Code::PING)),
        Ok(Signal::Ping { custody: false })
    );
    assert_eq!(
        Signal::decode(&with(Code::ABORT)),
        Ok(Signal::Abort(Abort {
            bad_csm_option: Some(OptionNumber(1152))
        }))
    );
    assert_eq!(
        Signal::decode(&with(Code::RELEASE)),
        Ok(Signal::Release(Release::default()))
    );
}

#[test]
fn rfc8323_5_2_unknown_options_elective_ignored_critical_abort() {
    // Option 6 (elective, unknown in a CSM) is ignored; so is a 5-byte Max-Message-Size
    // and a second one.
    let csm = frame(
        Code::CSM,
        &[],
        &[(2, &[1, 0]), (2, &[2, 0]), (6, b"x")],
        b"",
    );
    assert_eq!(
        Signal::decode(&csm),
        Ok(Signal::Csm(Csm {
            max_message_size: Some(256),
            block_wise_transfer: false
        }))
    );
    let too_long = frame(Code::CSM, &[], &[(2, &[1, 0, 0, 0, 0])], b"");
    assert_eq!(Signal::decode(&too_long), Ok(Signal::Csm(Csm::default())));

    // Option 3 is critical and unknown: abort, naming it when it came in a CSM.
    let err = Signal::decode(&frame(Code::CSM, &[], &[(3, b"")], b"")).unwrap_err();
    assert_eq!(
        err,
        SignalError::UnknownCritical {
            code: Code::CSM,
            number: OptionNumber(3)
        }
    );
    assert_eq!(
        err.abort(),
        Some(Abort {
            bad_csm_option: Some(OptionNumber(3))
        })
    );
    let err = Signal::decode(&frame(Code::PING, &[], &[(3, b"")], b"")).unwrap_err();
    assert_eq!(err.abort(), Some(Abort::default()));

    assert_eq!(
        Signal::decode(&frame(Code::GET, &[], &[], b"")),
        Err(SignalError::NotSignal(Code::GET))
    );
    let unknown = Code::new(7, 6);
    assert_eq!(
        Signal::decode(&frame(unknown, &[], &[], b"")),
        Err(SignalError::UnknownCode(unknown))
    );
    assert_eq!(SignalError::UnknownCode(unknown).abort(), None);
}

#[test]
fn release_and_abort_values_are_written_within_their_lengths() {
    let release = Signal::Release(Release {
        alternative_addresses: vec![String::new(), "x".repeat(256), "ok".to_owned()],
        hold_off_s: Some(u32::MAX),
    });
    let f = release.to_frame(Token::EMPTY, Bytes::new());
    assert_eq!(
        Signal::decode(&f),
        Ok(Signal::Release(Release {
            alternative_addresses: vec!["ok".to_owned()],
            hold_off_s: Some(Release::MAX_HOLD_OFF_S),
        }))
    );
}

// ------------------------------------------------------------------ properties

fn any_frame() -> impl Strategy<Value = Frame> {
    let code = prop_oneof![
        (0u8..=7).prop_map(|d| Code::new(0, d)),
        (2u8..=5, 0u8..32).prop_map(|(c, d)| Code::new(c, d)),
        (1u8..=5).prop_map(|d| Code::new(7, d)),
    ];
    let option = (
        prop_oneof![0u16..40, 250u16..300, 1000u16..=u16::MAX],
        proptest::collection::vec(any::<u8>(), 0..300),
    );
    (
        code,
        proptest::collection::vec(any::<u8>(), 0..=8),
        proptest::collection::vec(option, 0..6),
        prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..20),
            proptest::collection::vec(any::<u8>(), 250..300),
            proptest::collection::vec(any::<u8>(), 65790..65820),
        ],
    )
        .prop_map(|(code, token, options, payload)| {
            let mut opts = Options::new();
            for (number, value) in options {
                opts.push(OptionNumber(number), value);
            }
            Frame {
                code,
                token: Token::new(&token).unwrap(),
                options: opts,
                payload: payload.into(),
            }
        })
}

fn any_signal() -> impl Strategy<Value = Signal> {
    prop_oneof![
        (proptest::option::of(any::<u32>()), any::<bool>()).prop_map(|(max, bwt)| {
            Signal::Csm(Csm {
                max_message_size: max,
                block_wise_transfer: bwt,
            })
        }),
        any::<bool>().prop_map(|custody| Signal::Ping { custody }),
        any::<bool>().prop_map(|custody| Signal::Pong { custody }),
        (
            proptest::collection::vec("[a-z:/.0-9]{1,40}", 0..3),
            proptest::option::of(0..=Release::MAX_HOLD_OFF_S)
        )
            .prop_map(|(alternative_addresses, hold_off_s)| {
                Signal::Release(Release {
                    alternative_addresses,
                    hold_off_s,
                })
            }),
        proptest::option::of(any::<u16>()).prop_map(|n| Signal::Abort(Abort {
            bad_csm_option: n.map(OptionNumber)
        })),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn frames_round_trip_over_tcp_and_websockets(f in any_frame()) {
        let bytes = f.encode();
        prop_assert_eq!(bytes.len(), f.encoded_len());
        prop_assert_eq!(
            stream::decode(&bytes, MAX),
            Ok(Decoded::Frame { frame: f.clone(), consumed: bytes.len() })
        );
        let ws = f.encode_ws();
        prop_assert_eq!(ws.len(), f.ws_encoded_len());
        prop_assert_eq!(stream::decode_ws(&ws, MAX), Ok(f));
    }

    #[test]
    fn signals_round_trip(s in any_signal(), token in proptest::collection::vec(any::<u8>(), 0..=8)) {
        let f = s.to_frame(Token::new(&token).unwrap(), Bytes::new());
        let Ok(Decoded::Frame { frame, .. }) = stream::decode(&f.encode(), MAX) else {
            return Err(TestCaseError::fail("the signal's frame decodes"));
        };
        prop_assert_eq!(Signal::decode(&frame), Ok(s));
    }

    #[test]
    fn what_decodes_encodes_to_the_same_bytes(
        bytes in proptest::collection::vec(any::<u8>(), 0..64),
        cut in 0usize..64,
    ) {
        match stream::decode(&bytes, MAX) {
            Ok(Decoded::Frame { frame, consumed }) => {
                prop_assert_eq!(&frame.encode()[..], &bytes[..consumed]);
                // Any shorter prefix is incomplete, and asks for no more than is missing.
                let cut = cut.min(consumed.saturating_sub(1));
                match stream::decode(&bytes[..cut], MAX) {
                    Ok(Decoded::Incomplete { needed }) => prop_assert!(needed <= consumed - cut),
                    other => return Err(TestCaseError::fail(format!("{other:?}"))),
                }
            }
            Ok(Decoded::Incomplete { needed }) => prop_assert!(needed > 0),
            Err(_) => {}
        }
        if let Ok(frame) = stream::decode_ws(&bytes, MAX) {
            prop_assert_eq!(frame.encode_ws(), bytes);
        }
    }
}
