//! What the endpoint lends a layer while it acts ([`Context`]): the message layer, the
//! configuration, the event queue and the id counter, so that the client and server
//! layers own their behaviour without owning each other or the endpoint.

use std::collections::VecDeque;

use super::message::MessageLayer;
use super::types::Event;
use crate::config::{EndpointConfig, Limits};

/// The endpoint's shared parts, borrowed by a layer for one input.
pub(super) struct Context<'a> {
    /// The configuration (a shared reference: copied out, it outlives a reborrow of the
    /// context).
    pub(super) config: &'a EndpointConfig,
    pub(super) msg: &'a mut MessageLayer,
    pub(super) events: &'a mut VecDeque<Event>,
    next_id: &'a mut u64,
}

impl<'a> Context<'a> {
    pub(super) fn new(
        config: &'a EndpointConfig,
        msg: &'a mut MessageLayer,
        events: &'a mut VecDeque<Event>,
        next_id: &'a mut u64,
    ) -> Self {
        Self {
            config,
            msg,
            events,
            next_id,
        }
    }

    /// The limits on state, for as long as the context's borrow of the configuration.
    pub(super) fn limits(&self) -> &'a Limits {
        &self.config.limits
    }

    /// A new id for a request, a ping, a received request or an observation.
    pub(super) fn new_id(&mut self) -> u64 {
        *self.next_id += 1;
        *self.next_id
    }
}
