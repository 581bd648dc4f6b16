//! The server's clock as its clients see it: the receive and transmit times it stamps
//! into every answer whose request asks for them (the Server-Time option,
//! [`crate::timesync`]), the `/time` resource, the capture times of its frames, and
//! `serve --clock-offset-ms`, which shifts all of them together (a server whose clock is
//! off, for tests). It also counts the requests it answered: a Block2 continuation is
//! answered from the endpoint's store and never counted, so the count is of exchanges.

use std::sync::Arc;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use coap::{Code, ContentFormat, IncomingRequest, OptionNumber, Response};
use coap_net::{Around, Resource, Router, handler};

use crate::timesync::{SERVER_TIME, ServerTimes};

/// The server's clock and its count of answered requests.
#[derive(Debug, Default)]
pub(crate) struct ServerClock {
    offset_us: AtomicI64,
    answered: AtomicU64,
}

impl ServerClock {
    /// Shifts the clock by `offset_us` from the system's.
    pub(crate) fn set_offset_us(&self, offset_us: i64) {
        self.offset_us.store(offset_us, Ordering::Relaxed);
    }

    /// The shift from the system's clock, µs.
    pub(crate) fn offset_us(&self) -> i64 {
        self.offset_us.load(Ordering::Relaxed)
    }

    /// Now on this clock, µs since the UNIX epoch.
    pub(crate) fn now_us(&self) -> i64 {
        system_now_us() + self.offset_us()
    }

    /// A time of the system's clock (a frame's capture time, as the backends stamp it)
    /// on this clock.
    pub(crate) fn shift(&self, system_us: u64) -> u64 {
        let shifted = i64::try_from(system_us).unwrap_or(i64::MAX) + self.offset_us();
        u64::try_from(shifted).unwrap_or(0)
    }

    /// Requests answered so far (Block2 continuations excepted).
    pub(crate) fn answered(&self) -> u64 {
        self.answered.load(Ordering::Relaxed)
    }

    /// Puts the clock around every answer of `router` (its receive time taken before
    /// the request is answered, its transmit time once it is) and adds `/time`.
    pub(crate) fn install(self: &Arc<Self>, router: &Router) {
        let clock = self.clone();
        let around: Around = Arc::new(move |request: &IncomingRequest| {
            clock.answered.fetch_add(1, Ordering::Relaxed);
            if !request.options.contains(SERVER_TIME) {
                return Box::new(|_: &mut Response| {});
            }
            let received_us = clock.now_us();
            let clock = clock.clone();
            Box::new(move |response: &mut Response| {
                let times = ServerTimes {
                    received_us,
                    sent_us: clock.now_us().max(received_us),
                };
                response.options.set(SERVER_TIME, times.encode());
            })
        });
        router.set_around(around);
        let clock = self.clone();
        router.add(
            crate::api::paths::TIME,
            Resource::new()
                .get(handler(move |_| {
                    let clock = clock.clone();
                    async move {
                        let body = format!("{{\"unix_us\":{}}}", clock.now_us());
                        let mut r = Response::new(Code::CONTENT).with_payload(body);
                        r.options.set_uint(
                            OptionNumber::CONTENT_FORMAT,
                            u32::from(ContentFormat::JSON.0),
                        );
                        r
                    }
                }))
                .attr("rt", "coapcam.time"),
        );
    }
}

fn system_now_us() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_micros()).unwrap_or(i64::MAX))
}
