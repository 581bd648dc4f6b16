//! Compact point clouds: as the filtered depth they were computed from (65103), and
//! quantized to millimetres (65104). The layouts are the `compact` crate's
//! ([`compact::cloud`], [`compact::mm`]); here are the points they stand for.
//!
//! A camera's cloud is computed by [`DepthPart::points`], on the server when it grabs and
//! on the client when it decodes 65103: the same function on the same numbers, so the same
//! f32 bits (Rust never fuses a multiply and an add on its own, and the order of the
//! operations is the function's). Pixels whose points fall outside the region are zeroed
//! before sending: they carry nothing, and runs of zeros cost RVL almost nothing.

use compact::{cloud, mm};
use geometry::{Point3, PointCloud, Roi3, Transform};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use rgbd::{DepthFrame, DistortionModel, FilterError, Intrinsics};

use super::codec::{CameraFrame, Cloud, CloudSource, Decoders, EncodeError, Subject};
pub use super::codec::{DepthCloudError, DepthPart};

pub use compact::WireError;
pub use compact::cloud::CloudError;

impl DepthPart {
    /// What the camera saw: its pose in the common frame (the transform, then the
    /// correction) and its depth intrinsics.
    pub fn view(&self) -> geometry::View {
        let k = &self.intrinsics;
        let to_common = match &self.correction {
            Some(c) => self.transform.then(c),
            None => self.transform,
        };
        geometry::View::pinhole(to_common, k.fx, k.fy, k.ppx, k.ppy, k.width, k.height)
    }

    /// The cloud: each valid pixel deprojected, moved by the transform, kept when inside
    /// the region (row-major order), then moved by the correction. Pixels whose points
    /// were not kept become 0 in `depth`.
    pub fn points(&mut self) -> Result<Vec<Point3>, FilterError> {
        // Moved in place and kept by a flag a pixel: a second buffer of every pixel's
        // point (16 bytes each as an `Option`, 15 MB at 1280 x 720) was fresh pages on
        // every grab, under the server's fixed malloc threshold.
        let mut points = rgbd::deproject_frame(&self.depth, &self.intrinsics)?;
        let (transform, roi) = (&self.transform, &self.roi);
        points.par_iter_mut().for_each(|p| *p = transform.apply(p));
        let kept: Vec<bool> = points.par_iter().map(|p| roi.contains(p)).collect();
        let mut flags = kept.iter();
        let width = self.depth.width as usize;
        for row in self.depth.data.chunks_mut(self.depth.stride.max(1)) {
            for raw in row.iter_mut().take(width).filter(|raw| **raw != 0) {
                if flags.next() == Some(&false) {
                    *raw = 0;
                }
            }
        }
        let mut flags = kept.iter();
        points.retain(|_| flags.next() == Some(&true));
        points.shrink_to_fit();
        if let Some(c) = &self.correction {
            points.par_iter_mut().for_each(|p| *p = c.apply(p));
        }
        Ok(points)
    }
}

fn model_number(m: DistortionModel) -> u8 {
    match m {
        DistortionModel::None => 0,
        DistortionModel::ModifiedBrownConrady => 1,
        DistortionModel::InverseBrownConrady => 2,
        DistortionModel::BrownConrady => 4,
        DistortionModel::KannalaBrandt4 => 5,
    }
}

fn model_of(n: u8) -> DistortionModel {
    match n {
        1 => DistortionModel::ModifiedBrownConrady,
        2 => DistortionModel::InverseBrownConrady,
        4 => DistortionModel::BrownConrady,
        5 => DistortionModel::KannalaBrandt4,
        // compact::cloud::decode admits only 0, 1, 2, 4 and 5.
        _ => DistortionModel::None,
    }
}

fn transform_floats(t: &Transform) -> [f32; 12] {
    let (l, v) = (&t.linear, &t.translation);
    [
        l[(0, 0)],
        l[(0, 1)],
        l[(0, 2)],
        l[(1, 0)],
        l[(1, 1)],
        l[(1, 2)],
        l[(2, 0)],
        l[(2, 1)],
        l[(2, 2)],
        v.x,
        v.y,
        v.z,
    ]
}

fn transform_of(f: &[f32; 12]) -> Transform {
    Transform {
        linear: Matrix3::from_row_slice(&f[..9]),
        translation: Vector3::new(f[9], f[10], f[11]),
    }
}

/// Parts as a compact cloud (65103). Call [`DepthPart::points`] first: it zeroes the
/// pixels that carry nothing.
pub fn depth_cloud<'a>(
    parts: impl IntoIterator<Item = &'a DepthPart>,
) -> Result<Vec<u8>, EncodeError> {
    let parts: Vec<(cloud::Part, Vec<u8>)> = parts
        .into_iter()
        .map(|p| {
            let k = &p.intrinsics;
            let (min, max) = (p.roi.min(), p.roi.max());
            let head = cloud::Part {
                serial: p.serial.clone(),
                frame_number: p.depth.frame_number,
                timestamp_us: p.depth.timestamp_us,
                intrinsics: cloud::Intrinsics {
                    width: k.width,
                    height: k.height,
                    ppx: k.ppx,
                    ppy: k.ppy,
                    fx: k.fx,
                    fy: k.fy,
                    model: model_number(k.model),
                    coeffs: k.coeffs,
                },
                transform: transform_floats(&p.transform),
                roi: [min.x, min.y, min.z, max.x, max.y, max.z],
                correction: p.correction.as_ref().map(transform_floats),
            };
            (head, super::rvl::depth_rvl(&p.depth))
        })
        .collect();
    Ok(cloud::encode(parts.iter().map(|(h, d)| (h, &d[..])))?)
}

/// The parts of a compact cloud (65103); their points are [`DepthPart::points`].
pub fn parts_from_depth_cloud(payload: &[u8]) -> Result<Vec<DepthPart>, DepthCloudError> {
    let parts = cloud::decode(payload)?;
    parts
        .into_iter()
        .map(|(head, image)| {
            let k = head.intrinsics;
            let roi = Roi3::new(
                Point3::new(head.roi[0], head.roi[1], head.roi[2]),
                Point3::new(head.roi[3], head.roi[4], head.roi[5]),
            )?;
            Ok(DepthPart {
                serial: head.serial,
                depth: DepthFrame {
                    width: k.width,
                    height: k.height,
                    stride: k.width as usize,
                    depth_scale: image.depth_scale,
                    timestamp_us: head.timestamp_us,
                    frame_number: head.frame_number,
                    data: image.values,
                },
                intrinsics: Intrinsics {
                    width: k.width,
                    height: k.height,
                    ppx: k.ppx,
                    ppy: k.ppy,
                    fx: k.fx,
                    fy: k.fy,
                    model: model_of(k.model),
                    coeffs: k.coeffs,
                },
                transform: transform_of(&head.transform),
                roi,
                correction: head.correction.as_ref().map(transform_of),
            })
        })
        .collect()
}

/// The merged cloud of a compact cloud (65103): every part's points in order, the
/// cameras, and the newest grab's time.
pub fn cloud_from_depth_cloud(payload: &[u8]) -> Result<Cloud, DepthCloudError> {
    let mut out = Cloud {
        cloud: PointCloud::default(),
        serials: Vec::new(),
        timestamp_us: 0,
        views: Vec::new(),
        frames: Vec::new(),
    };
    for mut part in parts_from_depth_cloud(payload)? {
        out.cloud.points.extend(part.points()?);
        out.views.push(part.view());
        out.timestamp_us = out.timestamp_us.max(part.depth.timestamp_us);
        out.frames.push(CameraFrame {
            serial: part.serial.clone(),
            frame_number: part.depth.frame_number,
            timestamp_us: part.depth.timestamp_us,
        });
        out.serials.push(part.serial);
    }
    Ok(out)
}

/// A point cloud quantized to millimetres (65104).
pub fn cloud_mm(
    points: &[Point3],
    timestamp_us: u64,
    source: CloudSource<'_>,
) -> Result<Vec<u8>, EncodeError> {
    let serials: Vec<&str> = match source {
        CloudSource::Camera { serial, .. } => vec![serial.as_str()],
        CloudSource::Merged { serials } => serials.iter().map(|s| s.as_str()).collect(),
    };
    let xyz: Vec<[f32; 3]> = points.iter().map(|p| [p.x, p.y, p.z]).collect();
    Ok(mm::encode(timestamp_us, &serials, &xyz)?)
}

/// A quantized cloud (65104).
pub fn cloud_from_mm(payload: &[u8]) -> Result<Cloud, WireError> {
    let c = mm::decode(payload)?;
    Ok(Cloud {
        cloud: c
            .points
            .iter()
            .map(|p| Point3::new(p[0], p[1], p[2]))
            .collect(),
        serials: c.serials,
        timestamp_us: c.timestamp_us,
        views: Vec::new(),
        frames: Vec::new(),
    })
}

// ---- the rows of the table

/// The compact cloud's encoder: the depth the points were computed from.
pub fn encode_depth_cloud(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Cloud { parts, .. } => depth_cloud(parts),
        _ => Err(subject.not_served("compact cloud")),
    }
}

/// The millimetre cloud's encoder: the points.
pub fn encode_mm(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Cloud {
            points,
            timestamp_us,
            source,
            ..
        } => cloud_mm(points, timestamp_us, source),
        _ => Err(subject.not_served("millimetre cloud")),
    }
}

/// The compact cloud read back: deprojected, as the server did.
pub const DEPTH_CLOUD_DECODERS: Decoders = Decoders {
    cloud: Some(|body| Ok(cloud_from_depth_cloud(body)?)),
    ..Decoders::NONE
};

/// The millimetre cloud read back.
pub const MM_DECODERS: Decoders = Decoders {
    cloud: Some(|body| Ok(cloud_from_mm(body)?)),
    ..Decoders::NONE
};

#[cfg(test)]
mod tests {
    use super::*;
    use rand_chacha::ChaCha8Rng;
    use rand_core::{RngCore as _, SeedableRng as _};
    use rgbd::{PostProcessing, PostProcessingConfig};

    /// A 64 x 48 depth frame around 1 m with holes, rows padded to 70 values.
    fn frame(seed: u64) -> DepthFrame {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (width, height, stride) = (64u32, 48u32, 70usize);
        let data = (0..stride * height as usize)
            .map(|i| {
                let r = rng.next_u32();
                if i % stride >= width as usize || r % 11 == 0 {
                    0
                } else {
                    800 + (i % stride) as u16 * 3 + (r % 40) as u16
                }
            })
            .collect();
        DepthFrame {
            width,
            height,
            stride,
            depth_scale: 0.001,
            timestamp_us: 1_700_000_000_250_000,
            frame_number: 9,
            data,
        }
    }

    fn intrinsics(model: DistortionModel) -> Intrinsics {
        let coeffs = match model {
            DistortionModel::KannalaBrandt4 => [0.02, -0.01, 0.003, -0.001, 0.0],
            DistortionModel::None => [0.0; 5],
            _ => [0.12, -0.25, 0.001, -0.002, 0.08],
        };
        Intrinsics {
            width: 64,
            height: 48,
            ppx: 31.7,
            ppy: 24.2,
            fx: 60.3,
            fy: 60.1,
            model,
            coeffs,
        }
    }

    fn bits(points: &[Point3]) -> Vec<[u32; 3]> {
        points
            .iter()
            .map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect()
    }

    #[test]
    fn decoded_points_equal_the_senders_bit_for_bit_for_every_model_and_chain() {
        let chains = [
            r#"{}"#,
            r#"{"decimation": 1}"#,
            r#"{"spatial": 1}"#,
            r#"{"holefilling": 1}"#,
            r#"{"decimation": {"magnitude": 3}, "spatial": {"alpha": 0.4, "delta": 8, "iterations": 3, "holes_fill": 2}, "holefilling": {"mode": "nearest_from_around"}}"#,
        ];
        let transform = Transform {
            linear: Matrix3::new(0.98, -0.17, 0.02, 0.17, 0.98, -0.05, -0.01, 0.05, -0.99),
            translation: Vector3::new(0.03, -0.12, 1.41),
        };
        let roi =
            Roi3::new(Point3::new(-0.2, -0.3, 0.5), Point3::new(0.3, 0.2, 0.62)).expect("roi");
        let correction = Transform::from(nalgebra::Isometry3::new(
            Vector3::new(0.002, -0.001, 0.0),
            Vector3::new(0.0, 0.0, 0.01),
        ));
        for (seed, chain) in chains.iter().enumerate() {
            let config: PostProcessingConfig = serde_json::from_str(chain).expect(chain);
            for model in DistortionModel::ALL {
                let raw = frame(seed as u64);
                let mut post = PostProcessing::new(&config, Some(55.0)).expect("chain");
                let (processed, k) = post.process(&raw, &intrinsics(model)).expect("filters");
                // What the server computed before compact clouds existed.
                let all = rgbd::deproject_frame(processed, &k).expect("deprojects");
                let mut expected = transform.apply_and_crop(&all, &roi);
                correction.apply_in_place(&mut expected);
                let mut part = DepthPart {
                    serial: "840412060746".into(),
                    depth: processed.clone(),
                    intrinsics: k,
                    transform,
                    roi,
                    correction: Some(correction),
                };
                let sent = part.points().expect("points");
                assert_eq!(bits(&sent), bits(&expected.points), "{chain} {model:?}");
                assert!(
                    !sent.is_empty() && sent.len() < all.len(),
                    "{chain} {model:?}"
                );
                let payload = depth_cloud([&part]).expect("encodes");
                let mut parts = parts_from_depth_cloud(&payload).expect("decodes");
                assert_eq!(parts.len(), 1);
                let received = parts[0].points().expect("points");
                assert_eq!(bits(&received), bits(&sent), "{chain} {model:?}");
            }
        }
    }

    #[test]
    fn malformed_payloads_give_typed_errors() {
        assert!(matches!(
            cloud_from_depth_cloud(b"\x28\xb5\x2f\xfd garbage"),
            Err(DepthCloudError::Payload(CloudError::Wire(WireError::Zstd(
                _
            ))))
        ));
        assert!(matches!(cloud_from_mm(b""), Err(WireError::Zstd(_))));
    }
}
