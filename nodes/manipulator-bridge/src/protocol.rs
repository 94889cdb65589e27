//! The controller protocol: newline-delimited JSON over TCP.
//!
//! A controller sends commands, one JSON object per line:
//!
//! ```text
//! {"cmd": "approach", "cell": 3}            into cell 3 of the latest frame
//! {"cmd": "retract"}                        back out along the pipette axis
//! {"cmd": "goto", "x": 0, "y": 0, "z": -3850} to a point (scene frame, µm)
//! {"cmd": "home"}                           to the configured home
//! {"cmd": "stop"}                           emergency stop: wins over everything queued
//! ```
//!
//! `approach`, `retract`, `goto` and `home` take an optional `"speed"` (µm/s, capped at
//! the bridge's `max_speed`). The bridge sends every controller, one JSON object per line:
//! each frame's scene (the triangulate node's targets, with `"event": "scene"`), and the
//! events `plan`, `progress`, `arrived`, `blocked`, `stopped` and `error`. A malformed or
//! unknown command gets an `error` event on its own connection, which stays open.

use serde::{Deserialize, Serialize};

/// A command from a controller.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "kebab-case")]
pub enum Command {
    /// Into a cell of the latest frame.
    Approach {
        /// Its id in that frame.
        cell: u32,
        /// µm/s.
        #[serde(default)]
        speed: Option<f64>,
    },
    /// Out of the cell along the pipette axis, up to the safe height.
    Retract {
        /// µm/s.
        #[serde(default)]
        speed: Option<f64>,
    },
    /// To a point of the scene frame, µm.
    Goto {
        /// x.
        x: f64,
        /// y.
        y: f64,
        /// Height (`−Z` of the triangulation).
        z: f64,
        /// µm/s.
        #[serde(default)]
        speed: Option<f64>,
    },
    /// To the home position.
    Home {
        /// µm/s.
        #[serde(default)]
        speed: Option<f64>,
    },
    /// Stop now, dropping every queued command.
    Stop,
}

/// Reads one command line; `Err` is the message of the error event it gets.
pub fn parse_command(line: &str) -> Result<Command, String> {
    let v: serde_json::Value = serde_json::from_str(line).map_err(|e| {
        format!("not a JSON object ({e}); send one command per line, e.g. {{\"cmd\": \"stop\"}}")
    })?;
    let Some(name) = v.get("cmd").and_then(|c| c.as_str()).map(str::to_owned) else {
        return Err(
            "no \"cmd\" in the command; commands: approach, retract, goto, home, stop".into(),
        );
    };
    let known = ["approach", "retract", "goto", "home", "stop"];
    if !known.contains(&name.as_str()) {
        return Err(format!(
            "unknown command '{name}'; commands: {}",
            known.join(", ")
        ));
    }
    let c: Command = serde_json::from_value(v).map_err(|e| format!("bad '{name}' command: {e}"))?;
    let speed = match &c {
        Command::Approach { speed, .. }
        | Command::Retract { speed }
        | Command::Goto { speed, .. }
        | Command::Home { speed } => *speed,
        Command::Stop => None,
    };
    if speed.is_some_and(|s| !s.is_finite() || s <= 0.0) {
        return Err(format!("bad '{name}' command: speed must be positive µm/s"));
    }
    if let Command::Goto { x, y, z, .. } = c
        && ![x, y, z].iter().all(|v| v.is_finite())
    {
        return Err("bad 'goto' command: x, y and z must be numbers".into());
    }
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_parse_and_bad_ones_say_why() {
        assert_eq!(
            parse_command(r#"{"cmd":"approach","cell":3}"#).unwrap(),
            Command::Approach {
                cell: 3,
                speed: None
            }
        );
        assert_eq!(
            parse_command(r#"{"cmd":"goto","x":1,"y":-2,"z":3.5,"speed":50}"#).unwrap(),
            Command::Goto {
                x: 1.0,
                y: -2.0,
                z: 3.5,
                speed: Some(50.0)
            }
        );
        assert_eq!(parse_command(r#"{"cmd":"stop"}"#).unwrap(), Command::Stop);
        let e = parse_command("approach 3").unwrap_err();
        assert!(e.starts_with("not a JSON object"), "{e}");
        let e = parse_command(r#"{"cmd":"dance"}"#).unwrap_err();
        assert!(e.contains("unknown command 'dance'"), "{e}");
        let e = parse_command(r#"{"cell":3}"#).unwrap_err();
        assert!(e.contains("no \"cmd\""), "{e}");
        let e = parse_command(r#"{"cmd":"approach"}"#).unwrap_err();
        assert!(
            e.contains("bad 'approach' command") && e.contains("cell"),
            "{e}"
        );
        let e = parse_command(r#"{"cmd":"home","speed":-1}"#).unwrap_err();
        assert!(e.contains("speed must be positive"), "{e}");
    }
}
