//! Stream-mode tables: which (format, resolution, fps) a camera offers.
//!
//! The D415 table follows thesis §3.3.3: color RGB8/BGR8/RGBA8/BGRA8 at
//! 6/15/30/60 fps up to 1920x1080, with 1920x1080 limited to 30 fps; depth Z16 at
//! 6/15/25/30/60/90 fps up to 1280x720, with 1280x720 limited to 30 fps. The
//! resolutions are those `rs-enumerate-devices` lists for a D415.

use crate::frame::{ColorFormat, DepthFormat};

/// Which stream a mode or a refusal is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Stream {
    /// The color sensor.
    Color,
    /// The stereo depth sensor.
    Depth,
}

impl Stream {
    /// "color" or "depth".
    pub fn name(self) -> &'static str {
        match self {
            Self::Color => "color",
            Self::Depth => "depth",
        }
    }
}

/// A resolution and the frame rates it is offered at.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResolutionModes {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Frame rates offered at this resolution, ascending.
    pub fps: Vec<u32>,
}

/// Why a requested mode is not offered. The `Display` text is the diagnostic the
/// server sends with 4.00.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ModeError {
    /// The format name is not one of the stream's formats.
    #[error(
        "{} format \"{}\" is not offered; allowed: {allowed}",
        .stream.name(),
        crate::echo(.format)
    )]
    UnknownFormat {
        /// The stream.
        stream: Stream,
        /// The refused format name.
        format: String,
        /// The allowed names, comma-separated.
        allowed: String,
    },
    /// No mode has this width and height.
    #[error("{} resolution {width}x{height} is not offered; allowed: {allowed}", .stream.name())]
    ResolutionNotOffered {
        /// The stream.
        stream: Stream,
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
        /// The allowed resolutions, comma-separated.
        allowed: String,
    },
    /// The resolution exists but not at this frame rate.
    #[error("{} fps {fps} is not offered at {width}x{height}; allowed: {allowed:?}", .stream.name())]
    FpsNotOffered {
        /// The stream.
        stream: Stream,
        /// Requested frame rate.
        fps: u32,
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
        /// The frame rates offered at that resolution.
        allowed: Vec<u32>,
    },
}

/// The modes of one camera model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModeTable {
    /// Color formats offered (every color resolution in every format).
    pub color_formats: Vec<ColorFormat>,
    /// Color resolutions and their frame rates, largest first.
    pub color: Vec<ResolutionModes>,
    /// Depth formats offered.
    pub depth_formats: Vec<DepthFormat>,
    /// Depth resolutions and their frame rates, largest first.
    pub depth: Vec<ResolutionModes>,
}

/// D415 color resolutions (largest first).
pub const D415_COLOR_RESOLUTIONS: [(u32, u32); 9] = [
    (1920, 1080),
    (1280, 720),
    (960, 540),
    (848, 480),
    (640, 480),
    (640, 360),
    (424, 240),
    (320, 240),
    (320, 180),
];
/// D415 color frame rates (thesis §3.3.3).
pub const D415_COLOR_FPS: [u32; 4] = [6, 15, 30, 60];
/// D415 depth resolutions (largest first).
pub const D415_DEPTH_RESOLUTIONS: [(u32, u32); 6] = [
    (1280, 720),
    (848, 480),
    (640, 480),
    (640, 360),
    (480, 270),
    (424, 240),
];
/// D415 depth frame rates (thesis §3.3.3).
pub const D415_DEPTH_FPS: [u32; 6] = [6, 15, 25, 30, 60, 90];
/// The thesis limits the largest resolution of each stream to this frame rate.
pub const D415_MAX_RESOLUTION_FPS: u32 = 30;

fn table(resolutions: &[(u32, u32)], fps: &[u32]) -> Vec<ResolutionModes> {
    resolutions
        .iter()
        .enumerate()
        .map(|(i, &(width, height))| ResolutionModes {
            width,
            height,
            fps: fps
                .iter()
                .copied()
                .filter(|&f| i != 0 || f <= D415_MAX_RESOLUTION_FPS)
                .collect(),
        })
        .collect()
}

fn list_resolutions(modes: &[ResolutionModes]) -> String {
    modes
        .iter()
        .map(|m| format!("{}x{}", m.width, m.height))
        .collect::<Vec<_>>()
        .join(", ")
}

impl ModeTable {
    /// The Intel RealSense D415 table of thesis §3.3.3.
    pub fn d415() -> Self {
        Self {
            color_formats: ColorFormat::ALL.to_vec(),
            color: table(&D415_COLOR_RESOLUTIONS, &D415_COLOR_FPS),
            depth_formats: vec![DepthFormat::Z16],
            depth: table(&D415_DEPTH_RESOLUTIONS, &D415_DEPTH_FPS),
        }
    }

    fn modes(&self, stream: Stream) -> &[ResolutionModes] {
        match stream {
            Stream::Color => &self.color,
            Stream::Depth => &self.depth,
        }
    }

    /// Parses a color format name and checks that this table offers it.
    pub fn color_format(&self, name: &str) -> Result<ColorFormat, ModeError> {
        ColorFormat::from_name(name)
            .filter(|f| self.color_formats.contains(f))
            .ok_or_else(|| ModeError::UnknownFormat {
                stream: Stream::Color,
                format: name.to_owned(),
                allowed: self
                    .color_formats
                    .iter()
                    .map(|f| f.name())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }

    /// Parses a depth format name and checks that this table offers it.
    pub fn depth_format(&self, name: &str) -> Result<DepthFormat, ModeError> {
        DepthFormat::from_name(name)
            .filter(|f| self.depth_formats.contains(f))
            .ok_or_else(|| ModeError::UnknownFormat {
                stream: Stream::Depth,
                format: name.to_owned(),
                allowed: self
                    .depth_formats
                    .iter()
                    .map(|f| f.name())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }

    /// Checks that `stream` offers `width`x`height` at `fps`.
    pub fn check(
        &self,
        stream: Stream,
        width: u32,
        height: u32,
        fps: u32,
    ) -> Result<(), ModeError> {
        let modes = self.modes(stream);
        let Some(res) = modes
            .iter()
            .find(|m| m.width == width && m.height == height)
        else {
            return Err(ModeError::ResolutionNotOffered {
                stream,
                width,
                height,
                allowed: list_resolutions(modes),
            });
        };
        if res.fps.contains(&fps) {
            Ok(())
        } else {
            Err(ModeError::FpsNotOffered {
                stream,
                fps,
                width,
                height,
                allowed: res.fps.clone(),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn largest_resolutions_stop_at_30_fps() {
        let t = ModeTable::d415();
        assert_eq!(t.color[0].fps, vec![6, 15, 30]);
        assert_eq!(t.depth[0].fps, vec![6, 15, 25, 30]);
        assert_eq!(t.depth[1].fps, D415_DEPTH_FPS.to_vec());
    }
}
