//! Compiles `base-dictionary.txt` into the MCU role's data dictionary: the
//! JSON text Klipper hosts expect and its zlib compression, which `identify`
//! serves in chunks. Both land in OUT_DIR for `include_bytes!`.

use std::fmt::Write;
use std::{env, fs, path::PathBuf};

fn main() {
    let spec = fs::read_to_string("base-dictionary.txt").expect("base-dictionary.txt");
    println!("cargo:rerun-if-changed=base-dictionary.txt");
    let (mut commands, mut responses, mut constants) = (Vec::new(), Vec::new(), Vec::new());
    commands.push(("identify offset=%u count=%c".to_string(), 1));
    responses.push(("identify_response offset=%u data=%.*s".to_string(), 0));
    let mut next_id = 2;
    for (number, line) in spec.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (kind, rest) = line.split_once(' ').unwrap_or((line, ""));
        match kind {
            "command" => commands.push((rest.to_string(), next_id)),
            "response" => responses.push((rest.to_string(), next_id)),
            "constant" => {
                let (name, value) = rest.split_once(' ').unwrap_or((rest, ""));
                constants.push((name.to_string(), value.to_string()));
                continue;
            }
            _ => panic!(
                "base-dictionary.txt line {}: unknown kind '{kind}'",
                number + 1
            ),
        }
        next_id += 1;
    }
    let table = |entries: &[(String, i32)]| {
        let items: Vec<String> = entries
            .iter()
            .map(|(f, id)| format!("{:?}:{id}", f))
            .collect();
        format!("{{{}}}", items.join(","))
    };
    let mut config = String::new();
    for (i, (name, value)) in constants.iter().enumerate() {
        let sep = if i == 0 { "" } else { "," };
        let value = if value.parse::<i64>().is_ok() {
            value.clone()
        } else {
            format!("{value:?}")
        };
        write!(config, "{sep}{name:?}:{value}").expect("String");
    }
    let json = format!(
        "{{\"app\":\"onechip\",\"version\":\"v{}\",\"commands\":{},\"responses\":{},\"enumerations\":{{}},\"config\":{{{config}}}}}",
        env::var("CARGO_PKG_VERSION").expect("cargo sets it"),
        table(&commands),
        table(&responses),
    );
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    fs::write(out.join("dictionary.json"), &json).expect("write dictionary.json");
    let compressed = miniz_oxide::deflate::compress_to_vec_zlib(json.as_bytes(), 9);
    fs::write(out.join("dictionary.zlib"), compressed).expect("write dictionary.zlib");
}
