//! The controller protocol: newline-delimited JSON over TCP.
//!
//! A controller sends commands, one JSON object per line:
//!
//! ```text
//! {"cmd": "approach", "track": 17}          into the cell of track 17 (a track graph)
//! {"cmd": "approach", "cell": 3}            into cell 3 of the latest frame (no track node)
//! {"cmd": "retract"}                        back out along the pipette axis
//! {"cmd": "goto", "x": 0, "y": 0, "z": 3850}  to a point (camera frame, µm: Z the depth)
//! {"cmd": "home"}                           to the configured home
//! {"cmd": "stop"}                           emergency stop: wins over everything queued
//! ```
//!
//! `approach`, `retract`, `goto` and `home` take an optional `"speed"` (µm/s, capped at
//! the bridge's `max_speed`). The bridge sends every controller, one JSON object per line:
//! each frame's scene (the triangulate node's targets, with `"event": "scene"`), and the
//! events `plan`, `progress`, `arrived`, `blocked`, `stopped` and `error`. A malformed or
//! unknown command gets an `error` event on its own connection, which stays open; so does
//! a line that is not UTF-8. A line longer than [`MAX_LINE`] bytes gets an `error` event and
//! its connection is closed (a controller that sends no newline cannot make the bridge
//! buffer without end).

use serde::{Deserialize, Serialize};
use std::io::BufRead;

/// Longest command line the bridge reads, bytes (the newline not counted).
pub const MAX_LINE: usize = 64 * 1024;

/// One line from a controller, as [`read_line`] found it.
#[derive(Clone, Debug, PartialEq)]
pub enum Line {
    /// A line of text, without its newline (and a `\r` before it).
    Text(String),
    /// A line that is not UTF-8 (skipped whole).
    NotUtf8,
    /// A line longer than the limit: nothing more of the connection should be read.
    TooLong,
    /// The connection ended.
    End,
}

/// Reads one `\n`-terminated line of at most `max` bytes from `r`, never holding more than
/// `max` bytes of it. A last line without a newline counts as a line.
pub fn read_line(r: &mut impl BufRead, max: usize) -> std::io::Result<Line> {
    let mut buf = Vec::new();
    loop {
        let avail = match r.fill_buf() {
            Ok(a) => a,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if avail.is_empty() {
            if buf.is_empty() {
                return Ok(Line::End);
            }
            break;
        }
        let (take, done) = match avail.iter().position(|&b| b == b'\n') {
            Some(i) => (i, true),
            None => (avail.len(), false),
        };
        if buf.len() + take > max {
            return Ok(Line::TooLong);
        }
        buf.extend_from_slice(&avail[..take]);
        r.consume(take + usize::from(done));
        if done {
            break;
        }
    }
    if buf.last() == Some(&b'\r') {
        buf.pop();
    }
    Ok(String::from_utf8(buf).map_or(Line::NotUtf8, Line::Text))
}

/// `line` cut to its first `max` characters (with `…` where cut), for echoing it back.
pub fn shorten(line: &str, max: usize) -> String {
    match line.char_indices().nth(max) {
        Some((i, _)) => format!("{}…", &line[..i]),
        None => line.to_owned(),
    }
}

/// A command from a controller.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "kebab-case")]
pub enum Command {
    /// Into a cell: by its track where a track node feeds the bridge, else by its id in
    /// the latest frame.
    Approach {
        /// Its track's id.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        track: Option<u32>,
        /// Its id in the latest frame (only where no track node feeds the bridge).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        cell: Option<u32>,
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
    /// To a point of the camera frame, µm.
    Goto {
        /// x.
        x: f64,
        /// y.
        y: f64,
        /// Depth (the triangulation's Z: smaller is higher).
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

/// A JSON value read with every object's keys checked for repeats (serde_json keeps the
/// last of two equal keys without a word; a command must not mean what its first key hid).
struct Strict(serde_json::Value);

impl<'de> serde::Deserialize<'de> for Strict {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(StrictVisitor)
    }
}

struct StrictVisitor;

impl<'de> serde::de::Visitor<'de> for StrictVisitor {
    type Value = Strict;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a JSON value")
    }
    fn visit_bool<E>(self, v: bool) -> Result<Strict, E> {
        Ok(Strict(v.into()))
    }
    fn visit_i64<E>(self, v: i64) -> Result<Strict, E> {
        Ok(Strict(v.into()))
    }
    fn visit_u64<E>(self, v: u64) -> Result<Strict, E> {
        Ok(Strict(v.into()))
    }
    fn visit_f64<E>(self, v: f64) -> Result<Strict, E> {
        Ok(Strict(v.into()))
    }
    fn visit_str<E>(self, v: &str) -> Result<Strict, E> {
        Ok(Strict(v.into()))
    }
    fn visit_unit<E>(self) -> Result<Strict, E> {
        Ok(Strict(serde_json::Value::Null))
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Strict, A::Error> {
        let mut v = Vec::new();
        while let Some(Strict(e)) = seq.next_element()? {
            v.push(e);
        }
        Ok(Strict(v.into()))
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<Strict, A::Error> {
        let mut m = serde_json::Map::new();
        while let Some(k) = map.next_key::<String>()? {
            if m.contains_key(&k) {
                return Err(serde::de::Error::custom(format!(
                    "the key \"{k}\" is given twice"
                )));
            }
            let Strict(v) = map.next_value()?;
            m.insert(k, v);
        }
        Ok(Strict(m.into()))
    }
}

/// Reads one command line; `Err` is the message of the error event it gets.
///
/// A stop is read as leniently as safety asks: a byte-order mark before it, any letter
/// case (`{"cmd":"STOP"}`) and the bare word `stop` are all stops.
pub fn parse_command(line: &str) -> Result<Command, String> {
    let line = line.trim_start_matches('\u{feff}').trim();
    if line.eq_ignore_ascii_case("stop") {
        return Ok(Command::Stop);
    }
    let Strict(mut v) = serde_json::from_str(line).map_err(|e| {
        format!("not a JSON object ({e}); send one command per line, e.g. {{\"cmd\": \"stop\"}}")
    })?;
    let Some(name) = v
        .get("cmd")
        .and_then(|c| c.as_str())
        .map(str::to_ascii_lowercase)
    else {
        return Err(
            "no \"cmd\" in the command; commands: approach, retract, goto, home, stop".into(),
        );
    };
    if name == "stop" {
        return Ok(Command::Stop);
    }
    v["cmd"] = name.clone().into();
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
    if let Command::Approach { track, cell, .. } = c
        && track.is_some() == cell.is_some()
    {
        return Err(
            "bad 'approach' command: name the cell by \"track\" (its track id, e.g. {\"cmd\": \"approach\", \"track\": 17}) or, without a track node, by \"cell\" (its id in the latest frame); one of the two"
                .into(),
        );
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
    fn lines_are_read_within_the_limit_and_bad_bytes_cost_one_line() {
        // A BufReader of capacity 4 makes every line span several buffer fills.
        let data: &[u8] = b"ab\r\n\xff\xfe\n{\"cmd\":\"stop\"}\n123456789\nx\ntail";
        let mut r = std::io::BufReader::with_capacity(4, data);
        let got: Vec<Line> = (0..3).map(|_| read_line(&mut r, 8).unwrap()).collect();
        assert_eq!(
            got,
            vec![Line::Text("ab".into()), Line::NotUtf8, Line::TooLong]
        );
        // Within the limit every line comes whole, the last one without its newline too.
        let mut r = std::io::BufReader::with_capacity(4, data);
        let mut out = Vec::new();
        loop {
            match read_line(&mut r, 16).unwrap() {
                Line::End => break,
                l => out.push(l),
            }
        }
        assert_eq!(
            out,
            vec![
                Line::Text("ab".into()),
                Line::NotUtf8,
                Line::Text("{\"cmd\":\"stop\"}".into()),
                Line::Text("123456789".into()),
                Line::Text("x".into()),
                Line::Text("tail".into()),
            ]
        );
        assert_eq!(shorten("αβγδ", 2), "αβ…");
        assert_eq!(shorten("ab", 2), "ab");
    }

    #[test]
    fn commands_parse_and_bad_ones_say_why() {
        assert_eq!(
            parse_command(r#"{"cmd":"approach","cell":3}"#).unwrap(),
            Command::Approach {
                track: None,
                cell: Some(3),
                speed: None
            }
        );
        assert_eq!(
            parse_command(r#"{"cmd":"approach","track":17,"speed":20}"#).unwrap(),
            Command::Approach {
                track: Some(17),
                cell: None,
                speed: Some(20.0)
            }
        );
        let e = parse_command(r#"{"cmd":"approach","track":17,"cell":2}"#).unwrap_err();
        assert!(e.contains("one of the two"), "{e}");
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
            e.contains("bad 'approach' command") && e.contains("track") && e.contains("cell"),
            "{e}"
        );
        let e = parse_command(r#"{"cmd":"home","speed":-1}"#).unwrap_err();
        assert!(e.contains("speed must be positive"), "{e}");
    }

    #[test]
    fn any_spelling_of_stop_stops_and_repeated_keys_are_refused() {
        for l in [
            r#"{"cmd":"stop"}"#,
            r#"{"cmd":"STOP"}"#,
            r#"{"cmd":"Stop","speed":3}"#,
            "\u{feff}{\"cmd\":\"stop\"}",
            "\u{feff}STOP",
            " stop \r",
            "Stop",
        ] {
            assert_eq!(parse_command(l), Ok(Command::Stop), "{l:?}");
        }
        assert_eq!(
            parse_command("\u{feff}{\"cmd\":\"Home\"}"),
            Ok(Command::Home { speed: None })
        );
        // The last key does not win: the whole line is refused.
        for l in [
            r#"{"cmd":"stop","cmd":"approach","cell":1}"#,
            r#"{"cmd":"approach","cmd":"stop"}"#,
            r#"{"cmd":"goto","x":1,"y":2,"z":3,"x":900}"#,
        ] {
            let e = parse_command(l).unwrap_err();
            assert!(e.contains("is given twice"), "{l}: {e}");
        }
        assert!(parse_command("stopp").is_err());
    }
}
