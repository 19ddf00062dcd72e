//! Slots that bound what requests hold (`--max-heavy-reads`: a dataset or policy file in memory;
//! `--max-concurrent-uploads`: a temp file and a parser), shared so that one client cannot take
//! them all: a client holds at most half of them (at least one). A client is what the
//! per-address connection cap counts ([`Client`]), so four slow downloads from one host leave
//! the other half to everyone else, whatever they read at.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The client a request came from (an IPv4 address, or an IPv6 address's /64), as the
/// connection loop records it on every request it serves. A request without one (served
/// outside that loop) is counted only against the total.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Client(pub IpAddr);

/// The request's [`Client`], as a handler's argument: `None` for a request served outside the
/// connection loop.
pub struct RequestClient(pub Option<Client>);

impl<S: Send + Sync> axum::extract::FromRequestParts<S> for RequestClient {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        _state: &S,
    ) -> Result<Self, Self::Rejection> {
        Ok(RequestClient(parts.extensions.get::<Client>().copied()))
    }
}

/// Why a slot was refused.
#[derive(Debug, PartialEq, Eq)]
pub enum Refusal {
    /// This client holds its share already.
    ClientShare { share: usize },
    /// Every slot is taken.
    AllTaken,
}

/// `total` slots, of which one client holds at most [`ClientSlots::share`].
pub struct ClientSlots {
    total: usize,
    share: usize,
    slots: Arc<Semaphore>,
    held: Arc<Mutex<HashMap<Client, usize>>>,
}

impl ClientSlots {
    pub fn new(total: usize) -> Self {
        ClientSlots {
            total,
            share: total.div_ceil(2).max(1),
            slots: Arc::new(Semaphore::new(total)),
            held: Arc::default(),
        }
    }

    pub fn total(&self) -> usize {
        self.total
    }

    /// The most one client holds at once.
    pub fn share(&self) -> usize {
        self.share
    }

    /// Slots taken now.
    pub fn in_use(&self) -> usize {
        self.total - self.slots.available_permits()
    }

    /// A slot for `client`, held until the [`Slot`] is dropped, unless every slot is taken or
    /// the client holds its share (in that order: with every slot taken, that is the answer).
    /// Never waits.
    pub fn try_take(&self, client: Option<Client>) -> Result<Slot, Refusal> {
        let permit = self.slots.clone().try_acquire_owned().map_err(|_| Refusal::AllTaken)?;
        let share = client.map(|client| self.take_share(client)).transpose()?;
        Ok(Slot { _permit: permit, _share: share })
    }

    fn take_share(&self, client: Client) -> Result<Share, Refusal> {
        let mut held = self.held.lock().expect("client slots lock");
        let count = held.entry(client).or_insert(0);
        if *count >= self.share {
            return Err(Refusal::ClientShare { share: self.share });
        }
        *count += 1;
        Ok(Share { held: self.held.clone(), client })
    }
}

/// A slot taken; dropping it gives it (and the client's share of it) back.
pub struct Slot {
    _permit: OwnedSemaphorePermit,
    _share: Option<Share>,
}

struct Share {
    held: Arc<Mutex<HashMap<Client, usize>>>,
    client: Client,
}

impl Drop for Share {
    fn drop(&mut self) {
        let mut held = self.held.lock().expect("client slots lock");
        if let Some(count) = held.get_mut(&self.client) {
            *count -= 1;
            if *count == 0 {
                held.remove(&self.client);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn client(ip: &str) -> Option<Client> {
        Some(Client(ip.parse().unwrap()))
    }

    #[test]
    fn one_client_holds_half_and_the_rest_stays_for_the_others() {
        let slots = ClientSlots::new(4);
        let a = client("10.0.0.1");
        let first = [slots.try_take(a).unwrap(), slots.try_take(a).unwrap()];
        assert_eq!(slots.try_take(a).err(), Some(Refusal::ClientShare { share: 2 }));
        let others = [slots.try_take(client("10.0.0.2")).unwrap(), slots.try_take(None).unwrap()];
        assert_eq!(slots.in_use(), 4);
        assert_eq!(slots.try_take(client("10.0.0.3")).err(), Some(Refusal::AllTaken));
        drop(first);
        assert_eq!(slots.in_use(), 2);
        let again = [slots.try_take(a).unwrap(), slots.try_take(a).unwrap()];
        drop((again, others));
        assert_eq!((slots.in_use(), slots.held.lock().unwrap().len()), (0, 0), "all given back");
    }

    #[test]
    fn a_refused_total_gives_the_share_back() {
        let slots = ClientSlots::new(1);
        assert_eq!(slots.share(), 1);
        let held = slots.try_take(client("10.0.0.1")).unwrap();
        assert_eq!(slots.try_take(client("10.0.0.2")).err(), Some(Refusal::AllTaken));
        drop(held);
        assert!(slots.try_take(client("10.0.0.2")).is_ok(), "the refused client holds nothing");
        assert_eq!(ClientSlots::new(8).share(), 4);
        assert_eq!(ClientSlots::new(5).share(), 3);
    }
}
