//! What a node reports when it ends, for the supervisor's summary.

use serde::{Deserialize, Serialize};

/// The line prefix of a node's final statistics on its stdout.
pub const STATS_PREFIX: &str = "MICROSTEREO-STATS ";

/// What one node did, reported when it ends.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NodeStats {
    /// Node id.
    pub id: String,
    /// Frames consumed (steps taken; frames produced for a source).
    pub frames_in: u64,
    /// Messages published.
    pub frames_out: u64,
    /// Mean step time, ms.
    pub mean_ms: f64,
    /// 99th-percentile step time, ms.
    pub p99_ms: f64,
    /// What each input lost, in the order of the node's inputs.
    pub inputs: Vec<InputStats>,
    /// Mean time from capture to the end of this node's step, ms.
    pub latency_ms: f64,
    /// The last frame number handled.
    pub last_frame: Option<u64>,
    /// How many processes ran the node in the run (restarts + 1; set by [`merge`]).
    #[serde(default)]
    pub runs: u32,
    /// CPU time its process used (user and system, every thread), ms.
    #[serde(default)]
    pub cpu_ms: f64,
    /// Median time from capture to the end of this node's step, ms.
    #[serde(default)]
    pub latency_p50_ms: f64,
    /// 99th-percentile time from capture to the end of this node's step, ms.
    #[serde(default)]
    pub latency_p99_ms: f64,
    /// When its first step ended, ns since the Unix epoch (the run's sustained rate is
    /// measured from there, past the start-up).
    #[serde(default)]
    pub first_step_end_ns: Option<u64>,
    /// When its last step ended, ns since the Unix epoch.
    #[serde(default)]
    pub last_step_end_ns: Option<u64>,
    /// What it is doing before its first frame, while that takes long (a source rendering
    /// its loop ahead, say), with how far it got: `top` shows the node as preparing.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<String>,
}

impl NodeStats {
    /// Frames a second between the end of its first step and of its last: the rate it
    /// sustained, without the run's start-up and end (`None` under two steps).
    pub fn sustained_rate(&self) -> Option<f64> {
        let (a, b) = (self.first_step_end_ns?, self.last_step_end_ns?);
        (self.frames_in >= 2 && b > a)
            .then(|| (self.frames_in - 1) as f64 / ((b - a) as f64 * 1e-9))
    }
}

/// The mean of `v` (0 when empty).
pub fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        0.0
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// The `q` quantile of `v` (sorted in place; 0 when empty).
pub fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// CPU time this process has used so far (user and system, every thread), ms.
pub fn process_cpu_ms() -> f64 {
    // SAFETY: getrusage only writes the struct it is given, which is zeroed plain data.
    let usage = unsafe {
        let mut u: libc::rusage = std::mem::zeroed();
        if libc::getrusage(libc::RUSAGE_SELF, &mut u) != 0 {
            return 0.0;
        }
        u
    };
    let ms = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 / 1e3;
    ms(usage.ru_utime) + ms(usage.ru_stime)
}

/// What one input of a node lost.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct InputStats {
    /// The input's port.
    pub port: String,
    /// Messages lost on its edge.
    pub dropped: u64,
    /// Frames of the stream it never delivered, lost anywhere.
    pub missing: u64,
    /// The first frame number it delivered.
    #[serde(default)]
    pub first: Option<u64>,
    /// The last frame number it delivered.
    #[serde(default)]
    pub last: Option<u64>,
    /// The stream's last frame number, once its writer said the stream had ended.
    #[serde(default)]
    pub end: Option<u64>,
    /// Messages received (frames; markers aside).
    #[serde(default)]
    pub received: u64,
    /// The received frames' ages summed, ms: capture to receipt (a window's mean latency
    /// at this edge is the growth of this over the growth of `received`).
    #[serde(default)]
    pub age_ms_sum: f64,
}

/// One node's figures over every process that ran it (a restarted node's, in the order
/// they ran; a process that died reported last what it had done by then): frames and
/// drops summed, means weighted by frames, the worst 99th percentile, and on each input
/// the frames none of them received between one process's last and the next's first
/// counted as missing, and so are those after the last one received up to the stream's
/// end (no later frame shows their gap).
pub fn merge(runs: &[NodeStats]) -> Option<NodeStats> {
    let (first, rest) = runs.split_first()?;
    let mut m = first.clone();
    let weighted = |a: f64, na: u64, b: f64, nb: u64| {
        if na + nb == 0 {
            0.0
        } else {
            (a * na as f64 + b * nb as f64) / (na + nb) as f64
        }
    };
    for r in rest {
        m.mean_ms = weighted(m.mean_ms, m.frames_in, r.mean_ms, r.frames_in);
        m.latency_ms = weighted(m.latency_ms, m.frames_in, r.latency_ms, r.frames_in);
        // A median over several processes is not theirs weighted, but close to it.
        m.latency_p50_ms = weighted(m.latency_p50_ms, m.frames_in, r.latency_p50_ms, r.frames_in);
        m.latency_p99_ms = m.latency_p99_ms.max(r.latency_p99_ms);
        m.cpu_ms += r.cpu_ms;
        m.p99_ms = m.p99_ms.max(r.p99_ms);
        m.frames_in += r.frames_in;
        m.frames_out += r.frames_out;
        m.last_frame = m.last_frame.max(r.last_frame);
        m.first_step_end_ns = match (m.first_step_end_ns, r.first_step_end_ns) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        m.last_step_end_ns = m.last_step_end_ns.max(r.last_step_end_ns);
        // What the newest process is doing.
        m.phase = r.phase.clone();
        for (i, ri) in r.inputs.iter().enumerate() {
            match m.inputs.get_mut(i) {
                Some(mi) => {
                    let between = match (mi.last, ri.first) {
                        (Some(l), Some(f)) => f.saturating_sub(l + 1),
                        _ => 0,
                    };
                    mi.dropped += ri.dropped;
                    mi.received += ri.received;
                    mi.age_ms_sum += ri.age_ms_sum;
                    mi.missing += ri.missing + between;
                    mi.first = mi.first.or(ri.first);
                    mi.last = ri.last.or(mi.last);
                    mi.end = mi.end.max(ri.end);
                }
                None => m.inputs.push(ri.clone()),
            }
        }
    }
    for i in &mut m.inputs {
        if let Some(e) = i.end {
            i.missing += match i.last {
                Some(l) => e.saturating_sub(l),
                None => e + 1,
            };
        }
    }
    m.runs = runs.len() as u32;
    Some(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(
        frames: u64,
        mean: f64,
        p99: f64,
        input: (u64, u64, Option<u64>, Option<u64>),
    ) -> NodeStats {
        NodeStats {
            id: "match".into(),
            frames_in: frames,
            frames_out: 2 * frames,
            mean_ms: mean,
            p99_ms: p99,
            inputs: vec![InputStats {
                port: "left".into(),
                dropped: input.0,
                missing: input.1,
                first: input.2,
                last: input.3,
                end: None,
                received: frames,
                age_ms_sum: frames as f64 * mean,
            }],
            latency_ms: mean,
            last_frame: input.3,
            runs: 0,
            cpu_ms: frames as f64 * mean,
            latency_p50_ms: mean,
            latency_p99_ms: p99,
            first_step_end_ns: None,
            last_step_end_ns: None,
            phase: None,
        }
    }

    #[test]
    fn a_restarted_node_counts_every_process_and_the_frames_between_them() {
        // Frames 0..=5 by the first process (it died on 6), 9..=23 by the second: 6, 7
        // and 8 reached neither; one of the second's frames was dropped on its edge.
        let a = run(6, 10.0, 12.0, (0, 0, Some(0), Some(5)));
        let b = run(15, 20.0, 30.0, (1, 1, Some(9), Some(23)));
        let m = merge(&[a.clone(), b]).unwrap();
        assert_eq!((m.frames_in, m.frames_out, m.runs), (21, 42, 2));
        assert!((m.mean_ms - (60.0 + 300.0) / 21.0).abs() < 1e-12);
        assert_eq!(m.p99_ms, 30.0);
        assert_eq!(m.last_frame, Some(23));
        // CPU adds up over the processes; the latency's p99 is the worse one's.
        assert_eq!(m.cpu_ms, 6.0 * 10.0 + 15.0 * 20.0);
        assert_eq!(m.latency_p99_ms, 30.0);
        assert!((m.latency_p50_ms - (60.0 + 300.0) / 21.0).abs() < 1e-12);
        let i = &m.inputs[0];
        assert_eq!(
            (i.dropped, i.missing, i.first, i.last),
            (1, 4, Some(0), Some(23))
        );
        // Receipts and their ages add up (a window's edge latency is their growth's ratio).
        assert_eq!((i.received, i.age_ms_sum), (21, 60.0 + 300.0));
        // One process: as it reported.
        assert_eq!(
            merge(std::slice::from_ref(&a)),
            Some(NodeStats { runs: 1, ..a })
        );
        assert_eq!(merge(&[]), None);
    }

    #[test]
    fn the_sustained_rate_runs_from_the_first_step_to_the_last_over_every_process() {
        let s = 1_000_000_000u64;
        // 11 steps, the first ending at 5 s, the last at 7 s: 10 frames in 2 s.
        let mut a = run(11, 10.0, 12.0, (0, 0, Some(0), Some(10)));
        (a.first_step_end_ns, a.last_step_end_ns) = (Some(5 * s), Some(7 * s));
        assert_eq!(a.sustained_rate(), Some(5.0));
        // A restart: 9 more steps from 8 s to 9.5 s; 19 frames between 5 s and 9.5 s.
        let mut b = run(9, 10.0, 12.0, (0, 0, Some(12), Some(20)));
        (b.first_step_end_ns, b.last_step_end_ns) = (Some(8 * s), Some(9 * s + s / 2));
        let m = merge(&[a.clone(), b]).unwrap();
        assert_eq!(
            (m.first_step_end_ns, m.last_step_end_ns),
            (Some(5 * s), Some(9 * s + s / 2))
        );
        assert_eq!(m.sustained_rate(), Some(19.0 / 4.5));
        // One step, or none: no rate.
        let one = NodeStats {
            frames_in: 1,
            last_step_end_ns: Some(5 * s),
            ..a.clone()
        };
        assert_eq!(one.sustained_rate(), None);
        let none = NodeStats {
            first_step_end_ns: None,
            last_step_end_ns: None,
            ..a
        };
        assert_eq!(none.sustained_rate(), None);
    }

    #[test]
    fn frames_lost_after_the_last_one_received_count_once_the_stream_has_ended() {
        // Frames 0..=5, then the writer said the stream ended at 9: 6..=9 never came, and
        // no later frame shows their gap.
        let mut a = run(6, 10.0, 12.0, (0, 0, Some(0), Some(5)));
        a.inputs[0].end = Some(9);
        assert_eq!(
            merge(std::slice::from_ref(&a)).unwrap().inputs[0].missing,
            4
        );
        // A restarted process that got nothing before the end: everything after the first
        // process's last frame is missing, once.
        let mut b = run(0, 0.0, 0.0, (0, 0, None, None));
        b.inputs[0].end = Some(9);
        a.inputs[0].end = None;
        let m = merge(&[a, b.clone()]).unwrap();
        assert_eq!((m.inputs[0].missing, m.inputs[0].end), (4, Some(9)));
        // An input that never received a frame: the whole stream.
        assert_eq!(merge(&[b]).unwrap().inputs[0].missing, 10);
    }

    #[test]
    fn the_process_cpu_time_grows_with_work() {
        let start = process_cpu_ms();
        assert!(start > 0.0);
        // Spin until 20 ms of CPU are used (however long a loaded machine takes).
        let wall = std::time::Instant::now();
        let mut x = 1u64;
        while process_cpu_ms() < start + 20.0 {
            for _ in 0..100_000 {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
            assert!(wall.elapsed().as_secs() < 60, "no CPU time counted");
        }
    }
}
