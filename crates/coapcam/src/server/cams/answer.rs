//! The answers the grab and live resources make of a frame: its representation in a
//! content format, with the ETag of that representation and the frame's options.

use std::hash::{Hash as _, Hasher as _};

use coap::{Code, ContentFormat, OptionNumber, Response};
use rgbd::Serial;

use super::grab::Frame;
use crate::repr::no_depth::{self, NoDepth};
use crate::repr::{self, CloudSource, Stream, Subject};

pub(super) fn set_cf(r: &mut Response, cf: ContentFormat) {
    r.options
        .set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
}

/// Camera `sn`'s `frame` as what the representations encode (color as JPEG at `quality`).
pub(super) fn subject<'a>(sn: &'a Serial, frame: &'a Frame, quality: u8) -> Subject<'a> {
    match frame {
        Frame::Color(frame, intrinsics, depth_to_color) => Subject::Color {
            frame,
            intrinsics,
            depth_to_color,
            serial: sn,
            quality,
        },
        Frame::Depth(frame, intrinsics) => Subject::Depth {
            frame,
            intrinsics,
            serial: sn,
        },
        Frame::Cloud { points, part, .. } => Subject::Cloud {
            points,
            timestamp_us: part.depth.timestamp_us,
            source: CloudSource::Camera {
                serial: sn,
                frame: part.depth.frame_number,
            },
            parts: std::slice::from_ref(part),
        },
    }
}

/// `response` with the [`no_depth::NO_DEPTH`] option when `regions` are not empty.
pub(super) fn with_no_depth(mut response: Response, regions: &[NoDepth]) -> Response {
    if !regions.is_empty() {
        let mut largest = regions.to_vec();
        largest.sort_by(|a, b| b.area_m2.total_cmp(&a.area_m2));
        response
            .options
            .set(no_depth::NO_DEPTH, no_depth::encode(&largest));
    }
    response
}

/// `subject` in content format `cf` (one that [`negotiate`] chose), by its row of the table.
pub(super) fn encode(
    cf: ContentFormat,
    subject: &Subject<'_>,
) -> Result<Vec<u8>, repr::EncodeError> {
    match repr::Format::of(cf) {
        Some(row) => row.encode(subject),
        None => Err(repr::EncodeError::NotServed {
            stream: subject.stream_name(),
            format: "an unknown content format",
        }),
    }
}

/// A 2.05 Content of `body` in `cf` with ETag `etag`.
pub(super) fn content(body: Vec<u8>, cf: ContentFormat, etag: [u8; 8]) -> Response {
    let mut r = Response::new(Code::CONTENT).with_payload(body);
    set_cf(&mut r, cf);
    r.options.set(OptionNumber::ETAG, etag);
    r
}

/// The ETag of one representation of a frame: the frame's own for the thesis packet.
pub(super) fn representation_etag(
    frame: [u8; 8],
    cf: ContentFormat,
    quality: Option<u8>,
) -> [u8; 8] {
    if cf == ContentFormat::OCTET_STREAM {
        return frame;
    }
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (frame, cf.0).hash(&mut h);
    if let Some(q) = quality {
        q.hash(&mut h);
    }
    h.finish().to_be_bytes()
}

pub(super) fn frame_etag(sn: &Serial, kind: Stream, frame: &Frame) -> [u8; 8] {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    (
        sn.as_u64(),
        kind.index(),
        frame.frame_number(),
        frame.timestamp_us(),
    )
        .hash(&mut h);
    h.finish().to_be_bytes()
}
