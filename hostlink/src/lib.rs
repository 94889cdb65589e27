//! The graph's edges between hosts: iceoryx2's own link (`iceoryx2-link` with a
//! `iceoryx2-link-tunnel` over the Zenoh carrier of `iceoryx2-integrations`), run on a
//! thread beside a graph's part. Edges between nodes on one host stay shared memory; the
//! link mirrors the services it is told to (the edges that cross hosts, the parts' status)
//! into the other host's iceoryx2 domain, samples and wake-up events both ways.

use iceoryx2::config::Config;
use iceoryx2::prelude::*;
use iceoryx2_integrations_zenoh_link_carrier::ZenohCarrier;
use iceoryx2_link::Link;
use iceoryx2_link_tunnel::Tunnel;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// iceoryx2's link over Zenoh, on inter-process shared memory.
type ZenohLink = Link<ipc::Service, Tunnel<ZenohCarrier>>;

/// Where a link listens and whom it connects to.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Endpoints {
    /// Zenoh endpoints to listen on (`tcp/0.0.0.0:7447`).
    pub listen: Vec<String>,
    /// Zenoh endpoints of the other hosts to connect to (`tcp/capture-pc:7447`).
    pub connect: Vec<String>,
}

/// How often the link looks for services that appeared or went.
const DISCOVERY_PERIOD: Duration = Duration::from_millis(100);

/// Longest wait for data from the other side before the link looks at the local side
/// again (local samples do not wake it).
const POLL: Duration = Duration::from_micros(500);

/// How long [`HostLink::stop`] waits for the link's thread.
const STOP_PATIENCE: Duration = Duration::from_secs(2);

/// A link running on its own thread until [`HostLink::stop`] or drop.
pub struct HostLink {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// The Zenoh configuration of a link: peer mode, no multicast scouting (only the endpoints
/// given: another graph on the network must not join this one), and publication that
/// waits instead of dropping when the network is congested (frames are large, and an
/// edge may be lossless).
pub fn zenoh_config(e: &Endpoints) -> Result<zenoh::Config, String> {
    let mut z = zenoh::Config::default();
    let set = |z: &mut zenoh::Config, key: &str, value: String| {
        z.insert_json5(key, &value)
            .map_err(|err| format!("the Zenoh setting {key} = {value} was refused: {err}"))
    };
    let list = |v: &[String]| serde_json::to_string(v).expect("strings serialise");
    set(&mut z, "mode", "\"peer\"".into())?;
    set(&mut z, "scouting/multicast/enabled", "false".into())?;
    set(&mut z, "listen/endpoints", list(&e.listen))?;
    set(&mut z, "connect/endpoints", list(&e.connect))?;
    set(
        &mut z,
        "qos/publication",
        r#"[{key_exprs: ["**"], config: {congestion_control: "block"}}]"#.into(),
    )?;
    Ok(z)
}

impl HostLink {
    /// Starts a link in the iceoryx2 domain `config` that bridges the services `admit`
    /// accepts, over Zenoh at `endpoints`; returns once it runs (or why it cannot).
    pub fn start(
        config: Config,
        endpoints: &Endpoints,
        admit: impl Fn(&str) -> bool + Send + 'static,
    ) -> Result<Self, String> {
        let zenoh = zenoh_config(endpoints)?;
        // The link's writers give a sample up for a reader whose queue is full instead of
        // waiting for it. Each bridge also reads the service it writes (it skips its own
        // samples, but they fill its queue): a round that brings more samples than that
        // queue holds would wait for itself for ever; and one thread carries every edge, so
        // a wait on one slow reader would hold up all of them. A reader that falls so far
        // behind loses the frames (counted as dropped on its edge).
        let mut config = config;
        config.defaults.publish_subscribe.backpressure_strategy =
            iceoryx2::port::backpressure_strategy::BackpressureStrategy::DiscardData;
        // The carrier warns on each sample its inbox drops; the readers count them.
        set_log_level_from_env_or(LogLevel::Error);
        let stop = Arc::new(AtomicBool::new(false));
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<(), String>>();
        let flag = stop.clone();
        // The link holds iceoryx2 ports, which stay on the thread that made them.
        let thread = std::thread::Builder::new()
            .name("hostlink".into())
            .spawn(move || {
                let made = (|| -> Result<(ZenohLink, _), String> {
                    let node = NodeBuilder::new()
                        .config(&config)
                        .create::<ipc::Service>()
                        .map_err(|e| format!("cannot create the link's iceoryx2 node: {e:?}"))?;
                    let carrier = ZenohCarrier::create(zenoh).map_err(|e| {
                        format!("cannot open the Zenoh session (endpoints in use or unreachable?): {e:?}")
                    })?;
                    let mut link = Link::new(node, Tunnel::new(carrier, &config))
                        .with_filter(move |n: &ServiceName| admit(n.as_str()));
                    let listener = link
                        .listener()
                        .map_err(|e| format!("cannot create the link's wake-up: {e:?}"))?;
                    Ok((link, listener))
                })();
                let (mut link, listener) = match made {
                    Ok(l) => {
                        let _ = ready_tx.send(Ok(()));
                        l
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                        return;
                    }
                };
                let mut discovered = Instant::now() - DISCOVERY_PERIOD;
                while !flag.load(Ordering::Relaxed) {
                    if discovered.elapsed() >= DISCOVERY_PERIOD {
                        // A failed round leaves the link as it was; the next one tries again.
                        let _ = link.discover();
                        discovered = Instant::now();
                    }
                    let _ = link.propagate();
                    let _ = listener.timed_wait(|_| {}, POLL);
                }
                // One last round: what the graph sent before it stopped goes across.
                let _ = link.propagate();
            })
            .map_err(|e| format!("cannot start the link's thread: {e}"))?;
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(Self {
                stop,
                thread: Some(thread),
            }),
            Ok(Err(e)) => {
                let _ = thread.join();
                Err(e)
            }
            Err(_) => {
                let _ = thread.join();
                Err("the link's thread ended before it ran".into())
            }
        }
    }

    /// Stops the link after one last propagation.
    pub fn stop(mut self) {
        self.end();
    }

    fn end(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            // A send into a reader's full queue waits for it (a lossless edge): a reader that
            // stopped taking frames keeps the thread there. It is left behind, to end with
            // the process, rather than hold up the end of the run.
            let t0 = Instant::now();
            while !t.is_finished() && t0.elapsed() < STOP_PATIENCE {
                std::thread::sleep(Duration::from_millis(5));
            }
            if t.is_finished() {
                let _ = t.join();
            }
        }
    }
}

impl Drop for HostLink {
    fn drop(&mut self) {
        self.end();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_zenoh_configuration_takes_the_endpoints_and_turns_scouting_off() {
        let z = zenoh_config(&Endpoints {
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: vec!["tcp/10.0.0.2:7447".into()],
        })
        .unwrap();
        let json = format!("{z}");
        assert!(json.contains("tcp/127.0.0.1:7447"), "{json}");
        assert!(json.contains("tcp/10.0.0.2:7447"), "{json}");
        // An endpoint Zenoh cannot read is refused before anything opens.
        assert!(
            zenoh_config(&Endpoints {
                listen: vec!["no-such-protocol".into()],
                connect: vec![],
            })
            .is_err()
        );
    }
}
