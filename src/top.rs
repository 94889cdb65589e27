//! `microstereo top` (a running graph, live) and `microstereo topic list | hz | echo` (its
//! edges, for scripts): the flags, handed to the `monitor` crate.

use crate::error::CliError;
use clap::{Args, Subcommand};

/// Which running graph to look at.
#[derive(Args, Debug, Clone)]
pub struct Attach {
    /// The run: its instance (`run --instance`), `INSTANCE@HOST` for one part of a graph
    /// over hosts (default: the newest run on this machine).
    #[arg(long)]
    pub instance: Option<String>,
    /// The iceoryx2 domain it runs in (`run --domain`; default: $MICROSTEREO_DOMAIN, else
    /// the default domain).
    #[arg(long)]
    pub domain: Option<String>,
}

impl From<Attach> for monitor::Attach {
    fn from(a: Attach) -> Self {
        monitor::Attach {
            instance: a.instance,
            domain: a.domain,
        }
    }
}

/// Arguments of `microstereo top`.
#[derive(Args, Debug)]
pub struct TopArgs {
    #[command(flatten)]
    attach: Attach,
    /// Seconds between refreshes; the figures are over the last one.
    #[arg(long, default_value_t = 1.0)]
    interval: f64,
    /// Print one table measured over one interval and exit (for scripts); without a
    /// terminal, tables are printed every interval until the run ends.
    #[arg(long)]
    once: bool,
}

/// Runs `microstereo top`.
pub fn top(a: TopArgs) -> Result<(), CliError> {
    monitor::top(&monitor::TopOptions {
        attach: a.attach.into(),
        interval: a.interval,
        once: a.once,
    })
    .map_err(CliError::from)
}

/// Arguments of `microstereo topic`.
#[derive(Args, Debug)]
pub struct TopicArgs {
    #[command(subcommand)]
    command: TopicCommand,
}

#[derive(Subcommand, Debug)]
enum TopicCommand {
    /// Lists a running graph's edges: writer output, message, queue, readers.
    List(Attach),
    /// Measures an edge's message rate as it runs.
    Hz(EdgeArgs),
    /// Prints each message's header on an edge (not its pixels), then a summary.
    Echo(EdgeArgs),
}

/// Which edge of which run, and for how long.
#[derive(Args, Debug)]
struct EdgeArgs {
    /// The edge, as its writer's `NODE/OUTPUT` (`topic list` shows them).
    edge: String,
    #[command(flatten)]
    attach: Attach,
    /// Stop after this many lines (hz: reports; echo: messages); without it, until the
    /// run ends or Ctrl-C.
    #[arg(long)]
    count: Option<u64>,
    /// hz: seconds between reports (each over the messages since the last one).
    #[arg(long, default_value_t = 1.0)]
    window: f64,
}

impl From<EdgeArgs> for monitor::EdgeOptions {
    fn from(e: EdgeArgs) -> Self {
        monitor::EdgeOptions {
            edge: e.edge,
            attach: e.attach.into(),
            count: e.count,
            window: e.window,
        }
    }
}

/// Runs `microstereo topic`.
pub fn topic(a: TopicArgs) -> Result<(), CliError> {
    match a.command {
        TopicCommand::List(at) => monitor::list(&at.into()),
        TopicCommand::Hz(e) => monitor::hz(&e.into()),
        TopicCommand::Echo(e) => monitor::echo(&e.into()),
    }
    .map_err(CliError::from)
}
