//! A long render's progress, said every few seconds while it runs.

/// Says how far a long render got, every few seconds, until dropped.
pub struct RenderProgress {
    stop: Option<std::sync::mpsc::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl RenderProgress {
    /// Pixels of rendering (both views and the truth, over every scene) that take long
    /// enough to be worth a progress line: a 2048² scene takes seconds on two cores.
    pub const WORTH: usize = 3 * 2048 * 2048;

    /// Says `say` every `every` while `scenes` scenes of `width × height` render, when that
    /// is [`Self::WORTH`] it.
    pub fn start(
        (width, height, scenes): (usize, usize, usize),
        every: std::time::Duration,
        say: impl Fn(String) + Send + 'static,
    ) -> Self {
        let total_rows = (3 * height * scenes) as u64;
        if 3 * width * height * scenes < Self::WORTH {
            return Self {
                stop: None,
                thread: None,
            };
        }
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let start = std::time::Instant::now();
        let first = crate::rows_rendered();
        let thread = std::thread::spawn(move || {
            while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = rx.recv_timeout(every) {
                let done = (crate::rows_rendered() - first).min(total_rows);
                let f = done as f64 / total_rows as f64;
                let secs = start.elapsed().as_secs_f64();
                say(format!(
                    "rendering {width}×{height}{}: {:.0} % after {secs:.0} s{}",
                    if scenes > 1 {
                        format!(", {scenes} scenes")
                    } else {
                        String::new()
                    },
                    100.0 * f,
                    if f > 0.02 {
                        format!(", about {:.0} s to go", secs * (1.0 - f) / f)
                    } else {
                        String::new()
                    }
                ));
            }
        });
        Self {
            stop: Some(tx),
            thread: Some(thread),
        }
    }
}

impl Drop for RenderProgress {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CellSpec, Look, Optics, Scene};
    use std::sync::{Arc, Mutex};

    #[test]
    fn a_long_render_says_how_far_it_got() {
        let said: Arc<Mutex<Vec<String>>> = Arc::default();
        let optics = Optics {
            width: 1024,
            height: 1024,
            ..Optics::default()
        };
        let scene = Scene::random(optics, Look::default(), &CellSpec::default(), 1);
        {
            let said = said.clone();
            let _progress = RenderProgress::start(
                (1024, 1024, 4),
                std::time::Duration::from_millis(20),
                move |l| said.lock().unwrap().push(l),
            );
            for _ in 0..4 {
                let _ = scene.render();
            }
        }
        let said = said.lock().unwrap();
        let percent: Vec<f64> = said
            .iter()
            .map(|l| {
                assert!(l.starts_with("rendering 1024×1024, 4 scenes: "), "{l}");
                l.split(": ")
                    .nth(1)
                    .unwrap()
                    .split(' ')
                    .next()
                    .unwrap()
                    .parse()
                    .unwrap()
            })
            .collect();
        assert!(!percent.is_empty());
        assert!(percent.windows(2).all(|w| w[0] <= w[1]), "{said:?}");
        assert!(percent.iter().all(|&p| p <= 100.0), "{said:?}");
        // A small render says nothing.
        let quiet: Arc<Mutex<Vec<String>>> = Arc::default();
        let q = quiet.clone();
        drop(RenderProgress::start(
            (640, 480, 1),
            std::time::Duration::from_millis(1),
            move |l| q.lock().unwrap().push(l),
        ));
        assert!(quiet.lock().unwrap().is_empty());
    }
}
