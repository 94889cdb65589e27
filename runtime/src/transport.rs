//! Zero-copy edges over iceoryx2 shared memory.
//!
//! An edge is one iceoryx2 publish-subscribe service carrying a [`FrameHeader`] as user
//! header and a byte slice of any length (allocated by powers of two, so a frame may grow),
//! plus an event service of the same name whose notification wakes the readers: a node
//! sleeps in a WaitSet until one of its inputs has data — no busy loop, no polling.
//!
//! The writer loans a sample in shared memory and fills it in place; readers get a view of
//! that same memory. Per edge, the queue depth and what happens when it is full come from
//! the launch file ([`EdgeConfig`]): drop the oldest frame (default, for live video) or make
//! the writer wait (lossless edges). Readers count the messages lost on their edge from gaps
//! in the writer's per-edge count, and the frames they never saw (lost here or upstream)
//! from gaps in the frame numbers.

pub use crate::edge::{EdgeConfig, Overflow};
use iceoryx2::node::NodeWaitFailure;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::port_name::PortName;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use schemas::FrameHeader;
use std::cell::Cell;
use std::time::Duration;

/// The iceoryx2 service flavour: inter-process shared memory.
pub type Service = ipc::Service;

/// A received message: header and payload live in shared memory until it is dropped.
pub type Message = Sample<Service, [u8], FrameHeader>;

/// Why an edge cannot be opened or used.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    /// The edge name is not a valid iceoryx2 service name.
    #[error("'{0}' is not a valid edge name")]
    Name(String),
    /// iceoryx2 refused an operation.
    #[error("edge '{edge}': {what} failed: {reason}")]
    Iceoryx {
        /// The edge.
        edge: String,
        /// The operation.
        what: &'static str,
        /// iceoryx2's reason.
        reason: String,
    },
}

fn fail(edge: &str, what: &'static str) -> impl FnOnce(&dyn std::fmt::Debug) -> TransportError {
    let edge = edge.to_string();
    move |e| TransportError::Iceoryx {
        edge,
        what,
        reason: format!("{e:?}"),
    }
}

/// One process's handle on the transport (an iceoryx2 node).
#[derive(Debug)]
pub struct Transport {
    node: Node<Service>,
}

/// The publish-subscribe half of an edge.
type EdgeData =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Service, [u8], FrameHeader>;
/// The wake-up half of an edge.
type EdgeEvents = iceoryx2::service::port_factory::event::PortFactory<Service>;

/// How long a named reader waits for its edge's writer before it is created anyway.
pub const WRITER_WAIT: Duration = Duration::from_secs(30);

/// Largest number of readers of one edge.
pub const MAX_READERS: usize = 16;

/// Largest number of writers of one edge: its node (a restarted one's successor while the
/// old one goes) and a host's link.
const MAX_WRITERS: usize = 4;

/// The reader-name prefix of a watcher ([`Transport::watcher`]): a reader outside the graph
/// (`topic hz`, `topic echo`) that a lossless writer never waits for.
pub const WATCHER_PREFIX: &str = "watch-";

/// Times a lossless edge sends again a frame that reached none of its connected readers
/// ([`EdgePublisher::send`]).
const LOSSLESS_RESENDS: u32 = 3;

/// This process's iceoryx2 configuration: its domain's ([`domain_config`]).
///
/// iceoryx2's default configuration without its own clean-up of dead nodes when a node
/// starts or ends or a service opens: that clean-up can wait forever (iceoryx2 0.10 waits for
/// shared memory that a process killed while creating it left with no size), so it happens
/// once per run, bounded, in [`crate::process::remove_stale_resources`].
pub fn iceoryx_config() -> &'static Config {
    static CONFIG: std::sync::OnceLock<Config> = std::sync::OnceLock::new();
    CONFIG.get_or_init(|| domain_config(domain().as_deref()))
}

/// Where iceoryx2 keeps the static configuration of service `name` with `pattern`.
pub fn service_config_path(
    name: &str,
    pattern: iceoryx2::service::messaging_pattern::MessagingPattern,
) -> Option<std::path::PathBuf> {
    use iceoryx2::service::service_hash::ServiceHash;
    let cfg = iceoryx_config();
    let n = ServiceName::new(name).ok()?;
    let hash =
        ServiceHash::new::<<Service as iceoryx2::service::Service>::ServiceNameHasher>(&n, pattern);
    Some(
        std::path::PathBuf::from(cfg.global.service_dir().to_string()).join(format!(
            "{}{}{}",
            cfg.global.prefix,
            hash.as_str(),
            cfg.global.service.static_config_storage_suffix
        )),
    )
}

/// Removes the static configurations of these services that iceoryx2 never finished making:
/// a process killed while making one leaves it "being set up" (owner read-write, not yet
/// read-only) for ever, and iceoryx2's clean-up of dead nodes does not remove it. Only for
/// services nobody can be making now (the caller holds their run's lock). Returns how many
/// were removed.
pub fn remove_unfinished_services(names: impl IntoIterator<Item = String>) -> usize {
    use iceoryx2::service::messaging_pattern::MessagingPattern;
    use std::os::unix::fs::PermissionsExt;
    let mut removed = 0;
    for name in names {
        for pattern in [MessagingPattern::PublishSubscribe, MessagingPattern::Event] {
            let Some(path) = service_config_path(&name, pattern) else {
                continue;
            };
            let unfinished = std::fs::metadata(&path)
                .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o777 == 0o600);
            if unfinished && std::fs::remove_file(&path).is_ok() {
                removed += 1;
            }
        }
    }
    removed
}

/// The environment variable naming the iceoryx2 domain a process joins (the supervisor
/// sets it for its nodes): graphs in different domains share no shared memory, even on one
/// machine; a host's link joins domains over the network.
pub const DOMAIN_ENV: &str = "MICROSTEREO_DOMAIN";

static DOMAIN: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();

/// Checks a domain name: it becomes part of shared-memory file names.
pub fn check_domain(d: &str) -> Result<(), String> {
    if d.is_empty()
        || d.len() > 32
        || !d
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_".contains(c))
    {
        return Err(format!(
            "domain '{}' is not a usable name: use 1 to 32 letters, digits, '-' or '_'",
            d.chars().take(40).collect::<String>()
        ));
    }
    Ok(())
}

/// Sets this process's iceoryx2 domain before its first edge: `d`, else the one
/// [`DOMAIN_ENV`] names, else the default one. A name that cannot be one is an error,
/// wherever it came from.
pub fn set_domain(d: Option<&str>) -> Result<(), String> {
    let from_env = std::env::var(DOMAIN_ENV).ok().filter(|v| !v.is_empty());
    let d = match (d, from_env.as_deref()) {
        (Some(d), _) => Some(d),
        (None, Some(e)) => {
            check_domain(e).map_err(|m| format!("${DOMAIN_ENV}: {m}"))?;
            Some(e)
        }
        (None, None) => None,
    };
    if let Some(d) = d {
        check_domain(d)?;
    }
    let want = d.map(String::from);
    let got = DOMAIN.get_or_init(|| want.clone());
    if *got != want {
        return Err("the domain was set after the transport started".into());
    }
    Ok(())
}

/// This process's iceoryx2 domain (`None`: the default one).
pub fn domain() -> Option<String> {
    DOMAIN
        .get_or_init(|| {
            std::env::var(DOMAIN_ENV)
                .ok()
                .filter(|d| check_domain(d).is_ok())
        })
        .clone()
}

/// iceoryx2's default configuration in `domain` (its own prefix of every shared-memory
/// resource), without its own clean-up of dead nodes.
pub fn domain_config(domain: Option<&str>) -> Config {
    let mut c = Config::global_config().clone();
    if let Some(d) = domain
        && let Ok(prefix) = iceoryx2::prelude::FileName::new(format!("ms_{d}_").as_bytes())
    {
        c.global.prefix = prefix;
    }
    c.global.node.cleanup_dead_nodes_on_creation = false;
    c.global.node.cleanup_dead_nodes_on_destruction = false;
    c.global.service.cleanup_dead_nodes_on_open = false;
    c
}

impl Transport {
    /// Joins the transport as `name` (shown by iceoryx2's tools).
    pub fn new(name: &str) -> Result<Self, TransportError> {
        // iceoryx2 warns on stderr that it runs on its default configuration, which is
        // what the graph wants; IOX2_LOG_LEVEL still overrides.
        set_log_level_from_env_or(LogLevel::Error);
        let node_name = NodeName::new(name).map_err(|_| TransportError::Name(name.into()))?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(iceoryx_config())
            .create::<Service>()
            .map_err(|e| fail(name, "creating the iceoryx2 node")(&e))?;
        Ok(Self { node })
    }

    /// Sleeps for `d`; false when the process was asked to stop (a stop signal:
    /// [`crate::signals`]), at once.
    pub fn sleep(&self, d: Duration) -> bool {
        let start = std::time::Instant::now();
        loop {
            if crate::signals::stop_requested() {
                return false;
            }
            let left = d.saturating_sub(start.elapsed());
            match self.node.wait(left) {
                Ok(()) if start.elapsed() >= d => return !crate::signals::stop_requested(),
                // Woken early (a signal that is not a stop, or an interrupted sleep).
                Ok(()) | Err(NodeWaitFailure::Interrupt) => {}
                Err(NodeWaitFailure::TerminationRequest) => {
                    crate::signals::request_stop();
                    return false;
                }
            }
        }
    }

    fn services(
        &self,
        edge: &str,
        cfg: &EdgeConfig,
    ) -> Result<(EdgeData, EdgeEvents), TransportError> {
        let name = ServiceName::new(edge).map_err(|_| TransportError::Name(edge.into()))?;
        let pubsub = self
            .node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .user_header::<FrameHeader>()
            .subscriber_max_buffer_size(cfg.depth.max(1))
            .subscriber_max_borrowed_samples(max_held(cfg))
            .enable_safe_overflow(cfg.overflow == Overflow::DropOldest)
            .max_subscribers(MAX_READERS)
            .max_publishers(MAX_WRITERS)
            .history_size(0)
            .open_or_create()
            .map_err(|e| fail(edge, "opening the publish-subscribe service")(&e))?;
        let event = self
            .node
            .service_builder(&name)
            .event()
            .max_listeners(MAX_READERS)
            .open_or_create()
            .map_err(|e| fail(edge, "opening the event service")(&e))?;
        Ok((pubsub, event))
    }

    /// The writing end of `edge`.
    pub fn publisher(&self, edge: &str, cfg: &EdgeConfig) -> Result<EdgePublisher, TransportError> {
        let (pubsub, event) = self.services(edge, cfg)?;
        let lenient = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let watchers = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let handler = {
            let (lenient, watchers) = (lenient.clone(), watchers.clone());
            move |info: &iceoryx2::port::BackpressureInfo| {
                // A watcher's full queue is skipped: looking at a graph must not slow it.
                let watcher = || {
                    watchers
                        .lock()
                        .is_ok_and(|w: std::sync::MutexGuard<Vec<u128>>| {
                            w.contains(&info.receiver_port_id)
                        })
                };
                if lenient.load(std::sync::atomic::Ordering::Relaxed) || watcher() {
                    iceoryx2::port::BackpressureAction::DiscardData
                } else {
                    iceoryx2::port::BackpressureAction::FollowBackpressureyStrategy
                }
            }
        };
        let publisher = pubsub
            .publisher_builder()
            .set_backpressure_handler(handler)
            .initial_max_slice_len(4096)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(match cfg.overflow {
                Overflow::DropOldest => {
                    iceoryx2::port::backpressure_strategy::BackpressureStrategy::DiscardData
                }
                Overflow::Block => {
                    iceoryx2::port::backpressure_strategy::BackpressureStrategy::RetryUntilDelivered
                }
            })
            .create()
            .map_err(|e| fail(edge, "creating the publisher")(&e))?;
        let notifier = event
            .notifier_builder()
            .create()
            .map_err(|e| fail(edge, "creating the notifier")(&e))?;
        Ok(EdgePublisher {
            edge: edge.into(),
            publisher,
            notifier,
            service: pubsub,
            sent: Cell::new(0),
            overflow: cfg.overflow,
            lenient,
            watchers,
            seen_readers: Cell::new(usize::MAX),
        })
    }

    /// A reader of a running graph's `edge` from outside it (`topic hz`, `topic echo`):
    /// the edge must exist; its writer never waits for this reader's full queue, so it
    /// may lose messages (counted as dropped) but never slows the graph.
    pub fn watcher(&self, edge: &str) -> Result<EdgeSubscriber, TransportError> {
        let name = ServiceName::new(edge).map_err(|_| TransportError::Name(edge.into()))?;
        let pubsub = self
            .node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .user_header::<FrameHeader>()
            .open()
            .map_err(|e| fail(edge, "opening the edge (is the graph running?)")(&e))?;
        let event = self
            .node
            .service_builder(&name)
            .event()
            .open()
            .map_err(|e| fail(edge, "opening the edge's events")(&e))?;
        let depth = pubsub.static_config().subscriber_max_buffer_size();
        let cfg = EdgeConfig {
            depth,
            overflow: if pubsub.static_config().has_safe_overflow() {
                Overflow::DropOldest
            } else {
                Overflow::Block
            },
        };
        let listener = event
            .listener_builder()
            .create()
            .map_err(|e| fail(edge, "creating the listener")(&e))?;
        let port = format!("{WATCHER_PREFIX}{}", std::process::id());
        let subscriber = pubsub
            .subscriber_builder()
            .buffer_size(depth.max(1))
            .name(&PortName::new(&port).map_err(|_| TransportError::Name(port.clone()))?)
            .create()
            .map_err(|e| fail(edge, "creating the subscriber")(&e))?;
        Ok(EdgeSubscriber::new(edge, subscriber, listener, cfg))
    }

    /// The reading end of `edge`.
    pub fn subscriber(
        &self,
        edge: &str,
        cfg: &EdgeConfig,
    ) -> Result<EdgeSubscriber, TransportError> {
        self.reader(edge, cfg, None)
    }

    /// The reading end of `edge` under `name`, which the writer can see
    /// ([`EdgePublisher::reader_names`]). A named reader is created only once the edge has
    /// its writer (within [`WRITER_WAIT`]): a subscriber connects to the publishers that
    /// exist when it is created, before the writer can see it, but to a later publisher
    /// only when it next receives. A writer that saw the name and sent two frames into a
    /// depth-1 queue before that lost the second: iceoryx2 drops a sample for a receiver
    /// that is not connected yet when its queue is full, even on a lossless edge.
    pub fn reader(
        &self,
        edge: &str,
        cfg: &EdgeConfig,
        name: Option<&str>,
    ) -> Result<EdgeSubscriber, TransportError> {
        self.reader_impl(edge, cfg, name, name.is_some())
    }

    /// A named reader of an edge whose writer is on another host: its writer here is the
    /// host's link, which bridges the edge only once a reader holds it, so the reader does
    /// not wait for it (the writer over there waits for this reader instead).
    pub fn remote_reader(
        &self,
        edge: &str,
        cfg: &EdgeConfig,
        name: &str,
    ) -> Result<EdgeSubscriber, TransportError> {
        self.reader_impl(edge, cfg, Some(name), false)
    }

    fn reader_impl(
        &self,
        edge: &str,
        cfg: &EdgeConfig,
        name: Option<&str>,
        wait_for_writer: bool,
    ) -> Result<EdgeSubscriber, TransportError> {
        let (pubsub, event) = self.services(edge, cfg)?;
        if wait_for_writer {
            use iceoryx2::service::port_factory::PortFactory;
            let t0 = std::time::Instant::now();
            while pubsub.dynamic_config().number_of_publishers() == 0 {
                if t0.elapsed() > WRITER_WAIT {
                    crate::errln!(
                        "warning: edge '{edge}' has no writer after {} s; reading it anyway",
                        WRITER_WAIT.as_secs()
                    );
                    break;
                }
                if !self.sleep(Duration::from_millis(1)) {
                    return Err(TransportError::Iceoryx {
                        edge: edge.into(),
                        what: "waiting for the writer",
                        reason: "the node was asked to stop".into(),
                    });
                }
            }
        }
        // The listener first: a writer that sees the subscriber may send (and notify) at once.
        let listener = event
            .listener_builder()
            .create()
            .map_err(|e| fail(edge, "creating the listener")(&e))?;
        let mut builder = pubsub.subscriber_builder().buffer_size(cfg.depth.max(1));
        if let Some(n) = name {
            builder = builder.name(&PortName::new(n).map_err(|_| TransportError::Name(n.into()))?);
        }
        let subscriber = builder
            .create()
            .map_err(|e| fail(edge, "creating the subscriber")(&e))?;
        Ok(EdgeSubscriber::new(edge, subscriber, listener, *cfg))
    }
}

impl EdgeSubscriber {
    fn new(
        edge: &str,
        subscriber: Subscriber<Service, [u8], FrameHeader>,
        listener: Listener<Service>,
        cfg: EdgeConfig,
    ) -> Self {
        Self {
            edge: edge.into(),
            subscriber,
            listener,
            cfg,
            first: Cell::new(None),
            last: Cell::new(None),
            last_on_edge: Cell::new(None),
            received: Cell::new(0),
            age_ms_sum: Cell::new(0.0),
            dropped: Cell::new(0),
            missing: Cell::new(0),
            end: Cell::new(None),
        }
    }
}

/// The writing end of an edge.
#[derive(Debug)]
pub struct EdgePublisher {
    edge: String,
    publisher: Publisher<Service, [u8], FrameHeader>,
    notifier: Notifier<Service>,
    service: EdgeData,
    sent: Cell<u64>,
    overflow: Overflow,
    /// While set, a send skips a reader whose queue is full instead of waiting for it
    /// (the publisher's back-pressure handler reads it).
    lenient: std::sync::Arc<std::sync::atomic::AtomicBool>,
    /// The port ids of the watchers connected ([`WATCHER_PREFIX`]), whose full queues the
    /// back-pressure handler skips.
    watchers: std::sync::Arc<std::sync::Mutex<Vec<u128>>>,
    /// How many readers the edge had when `watchers` was last made.
    seen_readers: Cell<usize>,
}

impl EdgePublisher {
    /// Loans `len` bytes of shared memory, lets `fill` write the payload in place, sends it
    /// with `header` and wakes the readers.
    pub fn send(
        &self,
        header: FrameHeader,
        len: usize,
        fill: impl FnMut(&mut [u8]),
    ) -> Result<(), TransportError> {
        self.send_impl(header, len, fill, false).map(|_| ())
    }

    /// [`send`](Self::send) with the capture time set once the payload is written (to time
    /// the hop alone).
    pub fn send_stamped(
        &self,
        header: FrameHeader,
        len: usize,
        fill: impl FnMut(&mut [u8]),
    ) -> Result<(), TransportError> {
        self.send_impl(header, len, fill, true).map(|_| ())
    }

    fn send_impl(
        &self,
        header: FrameHeader,
        len: usize,
        mut fill: impl FnMut(&mut [u8]),
        stamp: bool,
    ) -> Result<usize, TransportError> {
        use std::sync::atomic::Ordering::Relaxed;
        self.note_watchers();
        let mut tries = 0;
        let readers = loop {
            let mut sample = self
                .publisher
                .loan_slice_uninit(len)
                .map_err(|e| fail(&self.edge, "loaning a sample")(&e))?;
            *sample.user_header_mut() = FrameHeader {
                edge_sequence: self.sent.get(),
                ..header
            };
            // SAFETY: the payload is bytes in iceoryx2's shared-memory segment, a mapping of
            // a file whose every byte has a value (zero when the kernel made the page, else
            // what an earlier sample wrote), and a u8 has no invalid values; so no
            // uninitialised byte can be read. Every message encoder writes the whole payload
            // before it is sent (schemas' round-trip test writes each message over loans of
            // 0x00, 0xA5 and 0xFF and compares), so a reader of messages sees no stale byte
            // either (the hop benchmark's writer touches a byte a page: its reader reads
            // nothing else). Clearing the loan first cost 1.4 % of the default graph's CPU.
            let mut sample = unsafe { sample.assume_init() };
            fill(sample.payload_mut());
            if stamp {
                sample.user_header_mut().capture_ns = crate::edge::now_ns();
            }
            let readers = sample.send().map_err(|e| fail(&self.edge, "sending")(&e))?;
            // iceoryx2 0.10 gives up a blocked send to a reader whose queue is full when, at
            // that instant, it finds the connection not established ("no connected receiver
            // and the buffer is full"), and the frame reaches nobody without an error: seen
            // on a lossless edge with its reader connected, after the writer's memory grew
            // (0.3–0.6 % of runs of the growing-frames test below). A lossless edge sends
            // such a frame again while a reader is connected, a few times: a frame that
            // reached some of its readers is not sent twice.
            tries += 1;
            if readers > 0
                || tries > LOSSLESS_RESENDS
                || self.overflow != Overflow::Block
                || self.lenient.load(Relaxed)
                || self.readers(|_| String::new()).is_empty()
            {
                break readers;
            }
            std::thread::yield_now();
        };
        self.sent.set(self.sent.get() + 1);
        self.notifier
            .notify()
            .map_err(|e| fail(&self.edge, "notifying the readers")(&e))?;
        Ok(readers)
    }

    /// Sends a restart marker: node `node` of the graph started anew as restart
    /// `generation` of the run, so every frame after the marker on this edge comes from its
    /// successor and the frames its predecessor held are lost.
    pub fn send_restart(&self, generation: u64, node: &str) -> Result<(), TransportError> {
        let header = FrameHeader {
            sequence: generation,
            kind: RESTART_KIND,
            ..FrameHeader::default()
        };
        self.send(header, node.len(), |b| b.copy_from_slice(node.as_bytes()))
    }

    /// Sends an end marker: the writer has sent every frame it will, the stream's last
    /// frame number being `last`. A reader that waits for a frame lost upstream near the end
    /// of a run would otherwise wait for ever; and frames lost after the last one a reader
    /// got show as no gap, so only the end tells it they are missing.
    ///
    /// Returns how many readers it reached. A reader whose connection to this writer is not
    /// open yet (a restarted writer's readers open it when they next look) and whose queue
    /// is full is skipped by iceoryx2 even on a lossless edge; with `wait` false, a reader
    /// whose queue is full is skipped too instead of waited for.
    pub fn send_end(&self, last: u64, wait: bool) -> Result<usize, TransportError> {
        let header = FrameHeader {
            sequence: last,
            kind: END_KIND,
            ..FrameHeader::default()
        };
        use std::sync::atomic::Ordering::Relaxed;
        self.lenient.store(!wait, Relaxed);
        let sent = self.send_impl(header, 1, |b| b.fill(0), false);
        self.lenient.store(false, Relaxed);
        sent
    }

    /// Makes the list of watchers anew when the number of readers changed (a count read
    /// from shared memory: cheap enough for every send).
    fn note_watchers(&self) {
        use iceoryx2::service::port_factory::PortFactory;
        let n = self.service.dynamic_config().number_of_subscribers();
        if n == self.seen_readers.get() {
            return;
        }
        self.seen_readers.set(n);
        let mut ids = Vec::new();
        self.service.dynamic_config().list_subscribers(|s| {
            if s.subscriber_name.as_str().starts_with(WATCHER_PREFIX) {
                ids.push(s.subscriber_id.value());
            }
            CallbackProgression::Continue
        });
        if let Ok(mut w) = self.watchers.lock() {
            *w = ids;
        }
    }

    /// Whether the edge's writer waits for a reader with a full queue.
    pub fn lossless(&self) -> bool {
        self.overflow == Overflow::Block
    }

    /// The edge's name.
    pub fn edge(&self) -> &str {
        &self.edge
    }

    /// The readers connected to the edge now, one unique id each (a restarted reader has a
    /// new one though its name is its predecessor's).
    pub fn reader_ids(&self) -> Vec<String> {
        self.readers(|s| format!("{:?}", s.subscriber_id))
    }

    /// Names of the readers connected to the edge now (empty for unnamed ones).
    pub fn reader_names(&self) -> Vec<String> {
        self.readers(|s| s.subscriber_name.as_str().to_string())
    }

    /// `what` of each reader connected to the edge now.
    fn readers(
        &self,
        what: impl Fn(
            &iceoryx2::service::dynamic_config::publish_subscribe::SubscriberDetails,
        ) -> String,
    ) -> Vec<String> {
        use iceoryx2::service::port_factory::PortFactory;
        let mut out = Vec::new();
        self.service.dynamic_config().list_subscribers(|s| {
            out.push(what(s));
            CallbackProgression::Continue
        });
        out
    }
}

/// The reading end of an edge.
#[derive(Debug)]
pub struct EdgeSubscriber {
    edge: String,
    subscriber: Subscriber<Service, [u8], FrameHeader>,
    listener: Listener<Service>,
    cfg: EdgeConfig,
    first: Cell<Option<u64>>,
    last: Cell<Option<u64>>,
    last_on_edge: Cell<Option<u64>>,
    received: Cell<u64>,
    age_ms_sum: Cell<f64>,
    dropped: Cell<u64>,
    missing: Cell<u64>,
    end: Cell<Option<u64>>,
}

/// The header `kind` of a restart marker (no message kind of the schemas has it): a control
/// message of the transport, never a frame.
pub const RESTART_KIND: u32 = u32::MAX;

/// The header `kind` of an end marker ([`EdgePublisher::send_end`]), a control message too.
pub const END_KIND: u32 = u32::MAX - 1;

/// What a reader takes off its edge.
#[derive(Debug)]
pub enum Received {
    /// A frame's message.
    Frame(Message),
    /// A restart marker ([`EdgePublisher::send_restart`]): node `node` started anew as restart
    /// `generation` of the run somewhere upstream of this edge.
    Restart {
        /// The run's restart count when it started.
        generation: u64,
        /// The restarted node's id.
        node: String,
    },
    /// An end marker ([`EdgePublisher::send_end`]): no frame after this comes on the edge;
    /// `last` is the stream's last frame number.
    End {
        /// The stream's last frame number.
        last: u64,
    },
}

/// How many received messages a reader of an edge with `cfg` may hold at once (it holds
/// frames while it waits for the same frame on its other inputs); receiving more fails until
/// one is let go.
pub fn max_held(cfg: &EdgeConfig) -> usize {
    cfg.depth.max(1) + 2
}

impl EdgeSubscriber {
    /// The edge's settings.
    pub fn config(&self) -> EdgeConfig {
        self.cfg
    }

    /// Counts a message the reader received but let go unused among the dropped ones.
    pub fn discard(&self) {
        self.dropped.set(self.dropped.get() + 1);
        self.missing.set(self.missing.get() + 1);
    }

    /// The next queued frame message, if any (oldest first); restart and end markers are
    /// passed over.
    pub fn receive(&self) -> Result<Option<Message>, TransportError> {
        loop {
            match self.receive_item()? {
                None => return Ok(None),
                Some(Received::Frame(m)) => return Ok(Some(m)),
                Some(Received::Restart { .. } | Received::End { .. }) => {}
            }
        }
    }

    /// The next queued message or restart marker, if any (oldest first).
    pub fn receive_item(&self) -> Result<Option<Received>, TransportError> {
        let Some(m) = self
            .subscriber
            .receive()
            .map_err(|e| fail(&self.edge, "receiving")(&e))?
        else {
            return Ok(None);
        };
        let gap = |last: &Cell<Option<u64>>, now: u64| {
            // A number at or below the last one is a restarted writer counting anew.
            let g = last.get().map_or(0, |l| now.saturating_sub(l + 1));
            last.set(Some(now));
            g
        };
        let h = *m.user_header();
        self.dropped
            .set(self.dropped.get() + gap(&self.last_on_edge, h.edge_sequence));
        if h.kind == RESTART_KIND {
            return Ok(Some(Received::Restart {
                generation: h.sequence,
                node: String::from_utf8_lossy(m.payload()).into_owned(),
            }));
        }
        if h.kind == END_KIND {
            self.end.set(self.end.get().max(Some(h.sequence)));
            return Ok(Some(Received::End { last: h.sequence }));
        }
        self.missing
            .set(self.missing.get() + gap(&self.last, h.sequence));
        if self.first.get().is_none() {
            self.first.set(Some(h.sequence));
        }
        self.received.set(self.received.get() + 1);
        self.age_ms_sum.set(
            self.age_ms_sum.get()
                + crate::edge::now_ns().saturating_sub(h.capture_ns) as f64 * 1e-6,
        );
        Ok(Some(Received::Frame(m)))
    }

    /// Clears the wake-up events that brought the reader here.
    fn drain_events(&self) {
        let _ = self.listener.try_wait(|_| {});
    }

    /// Messages received so far.
    pub fn received(&self) -> u64 {
        self.received.get()
    }

    /// The received frames' ages at receipt (capture to receipt) summed, ms.
    pub fn age_ms_sum(&self) -> f64 {
        self.age_ms_sum.get()
    }

    /// Messages lost on this edge: overwritten in a full queue or let go unused.
    pub fn dropped(&self) -> u64 {
        self.dropped.get()
    }

    /// The first and the last frame number received, if any.
    pub fn frames_seen(&self) -> (Option<u64>, Option<u64>) {
        (self.first.get(), self.last.get())
    }

    /// The stream's last frame number, once an end marker told it.
    pub fn end(&self) -> Option<u64> {
        self.end.get()
    }

    /// Frames of the stream that never reached this reader's node, wherever they were lost
    /// (on this edge, upstream, or in a restarted writer): gaps in the frame numbers.
    pub fn missing(&self) -> u64 {
        self.missing.get()
    }

    /// The edge's name.
    pub fn edge(&self) -> &str {
        &self.edge
    }
}

/// Why waiting ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wake {
    /// These inputs (indices into the slice given) may have data.
    Ready,
    /// The timeout passed with no data.
    Timeout,
    /// The process was asked to stop (SIGINT / SIGTERM).
    Stop,
}

impl From<TransportError> for String {
    fn from(e: TransportError) -> Self {
        e.to_string()
    }
}

/// Sleeps in one WaitSet, built once, until one of `inputs` is notified, `timeout` passes or
/// a stop is requested, and calls `on_wake` with why and which inputs were notified; ends
/// after a stop, when `on_wake` returns `Ok(false)`, or with its error.
pub fn wait_loop<E: From<TransportError>>(
    inputs: &[&EdgeSubscriber],
    timeout: Duration,
    mut on_wake: impl FnMut(Wake, &[bool]) -> Result<bool, E>,
) -> Result<(), E> {
    let waitset = WaitSetBuilder::new()
        .create::<Service>()
        .map_err(|e| fail("waitset", "creating the waitset")(&e))?;
    let guards = inputs
        .iter()
        .map(|s| waitset.attach_notification(&s.listener))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| fail("waitset", "attaching an input")(&e))?;
    let mut ready = vec![false; inputs.len()];
    loop {
        ready.fill(false);
        let result = waitset
            .wait_and_process_once_with_timeout(
                |id| {
                    for (i, g) in guards.iter().enumerate() {
                        ready[i] |= id.has_event_from(g);
                    }
                    CallbackProgression::Continue
                },
                timeout,
            )
            .map_err(|e| fail("waitset", "waiting")(&e))?;
        for (s, _) in inputs.iter().zip(&ready).filter(|(_, r)| **r) {
            s.drain_events();
        }
        // Any signal interrupts the wait; the stop signals leave their flag.
        if result == iceoryx2::waitset::WaitSetRunResult::TerminationRequest {
            crate::signals::request_stop();
        }
        let wake = match result {
            _ if crate::signals::stop_requested() => Wake::Stop,
            _ if ready.contains(&true) => Wake::Ready,
            _ => Wake::Timeout,
        };
        if !on_wake(wake, &ready)? || wake == Wake::Stop {
            return Ok(());
        }
    }
}

/// One wait of [`wait_loop`]: marks in `ready` which inputs were notified.
pub fn wait_any(
    inputs: &[&EdgeSubscriber],
    timeout: Duration,
    ready: &mut Vec<bool>,
) -> Result<Wake, TransportError> {
    let mut wake = Wake::Timeout;
    wait_loop(inputs, timeout, |w, r| {
        wake = w;
        ready.clear();
        ready.extend_from_slice(r);
        Ok::<_, TransportError>(false)
    })?;
    Ok(wake)
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::{MessageKind, PixelFormat};

    fn edge_name(test: &str) -> String {
        format!("microstereo/test/{}/{test}", std::process::id())
    }

    fn header(seq: u64, len: usize) -> FrameHeader {
        FrameHeader {
            sequence: seq,
            ..FrameHeader::image(MessageKind::Image, PixelFormat::Mono8, len, 1, 1)
        }
    }

    #[test]
    fn frames_of_growing_size_arrive_bit_exact_and_wake_the_reader() {
        let _domain = crate::process::ReleaseDomain;
        let edge = edge_name("grow");
        let cfg = EdgeConfig {
            depth: 4,
            overflow: Overflow::Block,
        };
        let t = Transport::new("reader").unwrap();
        let sub = t.subscriber(&edge, &cfg).unwrap();
        // A publisher that goes away takes the samples nobody has read yet with it (its
        // memory is unmapped): the writer stays until the reader is done.
        let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
        let writer = {
            let edge = edge.clone();
            std::thread::spawn(move || {
                let t = Transport::new("writer").unwrap();
                let p = t.publisher(&edge, &cfg).unwrap();
                // 1 KiB to 4 MiB: the publisher's memory must grow on the way.
                for (seq, len) in [1024usize, 70_000, 1 << 20, 4 << 20, 3]
                    .into_iter()
                    .enumerate()
                {
                    p.send(header(seq as u64, len), len, |b| {
                        for (i, v) in b.iter_mut().enumerate() {
                            *v = ((i * 31 + seq * 7) % 251) as u8;
                        }
                    })
                    .unwrap();
                }
                done_rx.recv().unwrap();
            })
        };
        let mut got = Vec::new();
        let mut ready = Vec::new();
        while got.len() < 5 {
            let w = wait_any(&[&sub], Duration::from_secs(10), &mut ready).unwrap();
            assert_eq!(
                w,
                Wake::Ready,
                "woken by data, not by the timeout; got {got:?}"
            );
            while let Some(m) = sub.receive().unwrap() {
                let seq = m.user_header().sequence as usize;
                let ok = m
                    .payload()
                    .iter()
                    .enumerate()
                    .all(|(i, &v)| v == ((i * 31 + seq * 7) % 251) as u8);
                got.push((seq, m.payload().len(), ok));
            }
        }
        done_tx.send(()).unwrap();
        writer.join().unwrap();
        assert_eq!(
            got,
            vec![
                (0, 1024, true),
                (1, 70_000, true),
                (2, 1 << 20, true),
                (3, 4 << 20, true),
                (4, 3, true)
            ]
        );
        assert_eq!((sub.received(), sub.dropped()), (5, 0));
    }

    #[test]
    fn frames_lost_upstream_are_missing_but_not_dropped_here() {
        let _domain = crate::process::ReleaseDomain;
        let edge = edge_name("upstream");
        let cfg = EdgeConfig::default();
        let t = Transport::new("both").unwrap();
        let sub = t.subscriber(&edge, &cfg).unwrap();
        let p = t.publisher(&edge, &cfg).unwrap();
        // The writer never got frames 1, 2 and 4: they were lost before this edge.
        for seq in [0u64, 3, 5] {
            p.send(header(seq, 8), 8, |b| b.fill(0)).unwrap();
            assert!(sub.receive().unwrap().is_some());
        }
        assert_eq!((sub.received(), sub.dropped(), sub.missing()), (3, 0, 3));
        // A restarted writer counts its messages from 0 again: no loss on the edge, and the
        // frames it skipped while down are missing.
        drop(p);
        let p = t.publisher(&edge, &cfg).unwrap();
        for seq in [9u64, 10] {
            p.send(header(seq, 8), 8, |b| b.fill(0)).unwrap();
            assert!(sub.receive().unwrap().is_some());
        }
        assert_eq!((sub.received(), sub.dropped(), sub.missing()), (5, 0, 6));
    }

    #[test]
    fn an_end_marker_says_which_readers_it_missed_and_a_lenient_one_never_waits() {
        let _domain = crate::process::ReleaseDomain;
        let edge = edge_name("end");
        let cfg = EdgeConfig {
            depth: 1,
            overflow: Overflow::Block,
        };
        let t = Transport::new("both").unwrap();
        // The reader exists before the writer, as for a restarted writer: it opens its
        // connection to the writer only when it next receives.
        let sub = t.subscriber(&edge, &cfg).unwrap();
        let p = t.publisher(&edge, &cfg).unwrap();
        assert!(p.lossless());
        p.send(header(0, 8), 8, |b| b.fill(0)).unwrap();
        // The queue is full and the reader not connected: iceoryx2 skips it, lossless edge
        // or not, and the marker says it reached no reader.
        assert_eq!(p.send_end(0, true).unwrap(), 0);
        let m = sub.receive_item().unwrap();
        assert!(matches!(m, Some(Received::Frame(ref f)) if f.user_header().sequence == 0));
        drop(m);
        assert!(
            sub.receive_item().unwrap().is_none(),
            "the first marker was lost"
        );
        // Connected now: the marker sent again arrives.
        assert_eq!(p.send_end(0, false).unwrap(), 1);
        // The queue is full again; a lenient marker skips the reader instead of waiting.
        assert_eq!(p.send_end(0, false).unwrap(), 0);
        assert!(matches!(
            sub.receive_item().unwrap(),
            Some(Received::End { last: 0 })
        ));
        assert!(sub.receive_item().unwrap().is_none());
        assert_eq!(sub.end(), Some(0));
    }

    #[test]
    fn a_full_drop_oldest_queue_keeps_the_newest_and_counts_the_rest() {
        let _domain = crate::process::ReleaseDomain;
        let edge = edge_name("drop");
        let cfg = EdgeConfig {
            depth: 2,
            overflow: Overflow::DropOldest,
        };
        let t = Transport::new("both").unwrap();
        let sub = t.subscriber(&edge, &cfg).unwrap();
        let p = t.publisher(&edge, &cfg).unwrap();
        for seq in 0..10u64 {
            p.send(header(seq, 8), 8, |b| b.fill(seq as u8)).unwrap();
        }
        let mut seqs = Vec::new();
        while let Some(m) = sub.receive().unwrap() {
            assert!(
                m.payload()
                    .iter()
                    .all(|&v| v as u64 == m.user_header().sequence)
            );
            seqs.push(m.user_header().sequence);
        }
        assert_eq!(seqs, vec![8, 9]);
        // The first frame seen was 8: frames before the reader's first are not counted.
        assert_eq!((sub.received(), sub.dropped()), (2, 0));
        for seq in 10..15u64 {
            p.send(header(seq, 8), 8, |b| b.fill(seq as u8)).unwrap();
        }
        while sub.receive().unwrap().is_some() {}
        assert_eq!((sub.received(), sub.dropped()), (4, 3));
        assert_eq!(sub.missing(), 3);
        let mut ready = Vec::new();
        // Nothing new: the wait ends by its timeout.
        let _ = wait_any(&[&sub], Duration::from_millis(1), &mut ready).unwrap();
        assert_eq!(
            wait_any(&[&sub], Duration::from_millis(20), &mut ready).unwrap(),
            Wake::Timeout
        );
    }

    #[test]
    fn a_watcher_that_never_reads_does_not_hold_up_a_lossless_writer() {
        let _domain = crate::process::ReleaseDomain;
        let edge = edge_name("watched");
        let cfg = EdgeConfig {
            depth: 1,
            overflow: Overflow::Block,
        };
        let t = Transport::new("watched").unwrap();
        let p = t.publisher(&edge, &cfg).unwrap();
        let reader = t.reader(&edge, &cfg, Some("graph.in")).unwrap();
        // A watcher of an edge that is not there: one clear error, nothing created.
        assert!(t.watcher(&edge_name("no-such-edge")).is_err());
        let watcher = t.watcher(&edge).unwrap();
        assert_eq!(watcher.config(), cfg);
        // The graph's reader takes every frame; the watcher none until the end. Without the
        // skip, the second send would wait for the watcher's full queue for ever.
        for seq in 0..20u64 {
            p.send(header(seq, 8), 8, |b| b.fill(seq as u8)).unwrap();
            let m = reader
                .receive()
                .unwrap()
                .expect("the graph's reader gets every frame");
            assert_eq!(m.user_header().sequence, seq);
        }
        let mut seen = Vec::new();
        while let Some(m) = watcher.receive().unwrap() {
            seen.push(m.user_header().sequence);
        }
        // It kept the first frame its queue took and lost the rest, counted.
        assert_eq!(seen, vec![0]);
        p.send(header(20, 8), 8, |b| b.fill(20)).unwrap();
        assert_eq!(
            watcher.receive().unwrap().unwrap().user_header().sequence,
            20
        );
        assert_eq!((watcher.received(), watcher.dropped()), (2, 19));
        assert_eq!(reader.received(), 20);
    }
}
