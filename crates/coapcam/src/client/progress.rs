//! Progress bars on standard error for transfers over 1 MB (indicatif draws nothing when
//! standard error is not a terminal).

use coap_net::Progress;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use tokio::sync::mpsc;

/// A bar that appears once a transfer passes [`Bar::SHOW_ABOVE`] bytes.
pub struct Bar {
    enabled: bool,
    group: Option<MultiProgress>,
    bar: Option<ProgressBar>,
}

impl Bar {
    /// Transfers larger than this show a bar.
    pub const SHOW_ABOVE: usize = 1 << 20;

    /// A bar of its own (none when `enabled` is false).
    pub fn new(enabled: bool) -> Self {
        Self {
            enabled,
            group: None,
            bar: None,
        }
    }

    /// A bar among `group`'s, one line each, for transfers that run at once.
    pub fn in_group(group: &MultiProgress) -> Self {
        Self {
            enabled: true,
            group: Some(group.clone()),
            bar: None,
        }
    }

    /// `done` bytes of `total` (if known) have arrived.
    pub fn show(&mut self, done: usize, total: Option<usize>) {
        if !self.enabled {
            return;
        }
        if self.bar.is_none() && total.unwrap_or(done).max(done) > Self::SHOW_ABOVE {
            let bar = ProgressBar::new(total.unwrap_or(0) as u64);
            bar.set_style(
                ProgressStyle::with_template(
                    "{bar:40} {bytes}/{total_bytes} {bytes_per_sec} {eta}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
            );
            self.bar = Some(match &self.group {
                Some(group) => group.add(bar),
                None => bar,
            });
        }
        if let Some(bar) = &self.bar {
            bar.set_position(done as u64);
        }
    }

    /// The transfer ended: the bar goes.
    pub fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
            if let Some(group) = &self.group {
                group.remove(&bar);
            }
        }
    }

    /// Shows what arrives on `progress` until its sender is dropped, then finishes.
    pub async fn follow(mut self, mut progress: mpsc::UnboundedReceiver<Progress>) {
        while let Some(p) = progress.recv().await {
            self.show(p.done, p.total);
        }
        self.finish();
    }
}
