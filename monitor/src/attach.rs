//! Finding a running graph and its first snapshot.

use crate::Error;
use runtime::status::{self, GraphStatus, StatusReader};
use std::time::Duration;

/// How long `top` and `topic` wait for a named run's status to appear.
const ATTACH_PATIENCE: Duration = Duration::from_secs(3);

/// Which running graph to look at.
#[derive(Debug, Clone, Default)]
pub struct Attach {
    /// The run: an instance, or `INSTANCE@HOST` for one part of a graph over hosts
    /// (`None`: the newest run on this machine).
    pub instance: Option<String>,
    /// The iceoryx2 domain it runs in (`None`: $MICROSTEREO_DOMAIN, else the default).
    pub domain: Option<String>,
}

impl Attach {
    /// The instance to attach to: the one named, or the newest running.
    fn resolve(&self) -> Result<String, Error> {
        match &self.instance {
            Some(i) => Ok(i.clone()),
            None => status::running_instances()
                .into_iter()
                .next()
                .ok_or(Error::NoRun),
        }
    }

    /// Attaches to the run and takes its first snapshot.
    pub(crate) fn open(&self) -> Result<(StatusReader, GraphStatus), Error> {
        runtime::transport::set_domain(self.domain.as_deref()).map_err(Error::Status)?;
        let instance = self.resolve()?;
        let reader = StatusReader::open(&instance, ATTACH_PATIENCE).map_err(Error::Status)?;
        let first = reader
            .next(ATTACH_PATIENCE)
            .map_err(Error::Status)?
            .ok_or_else(|| Error::NoStatus {
                instance,
                secs: ATTACH_PATIENCE.as_secs(),
            })?;
        Ok((reader, first))
    }
}

/// Checks a refresh interval in seconds; `flag` names it in the error.
pub(crate) fn interval(flag: &'static str, s: f64) -> Result<Duration, Error> {
    if !(0.05..=3600.0).contains(&s) {
        return Err(Error::Interval { flag, seconds: s });
    }
    Ok(Duration::from_secs_f64(s))
}
