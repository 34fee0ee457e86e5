//! The run's summary as JSON, for tests and scripts that compare runs
//! (a print through a serial host against the same file run from the
//! SD folder).

use crate::Summary;
use serde_json::{Value, json};

impl Summary {
    /// What the run did, machine-readable: lines run, print time (s),
    /// final G-code position (X, Y, Z, E, mm), each stepper's step count,
    /// final position (steps) and last step (s), errors (`[line, text]`)
    /// and the MCU's shutdown message (or null).
    pub fn to_json(&self) -> Value {
        json!({
            "lines": self.lines,
            "print_time": self.print_time,
            "final_position": self.final_position,
            "steppers": self.steppers.iter().map(|s| json!({
                "name": s.name,
                "steps": s.steps,
                "position": s.position,
                "last_step": s.last_step.map(|clock| clock as f64 / self.mcu_freq),
            })).collect::<Vec<_>>(),
            "errors": self.errors,
            "shutdown": self.shutdown,
        })
    }
}

#[cfg(test)]
mod tests {
    use std::path::{Path, PathBuf};

    /// An SD folder with the shipped printer.cfg and `gcode`.
    fn sd(name: &str, gcode: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("onechip-json-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let shipped = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../sdcard-configs/octopus-pro-h723/printer.cfg");
        std::fs::copy(shipped, dir.join("printer.cfg")).expect("cfg");
        std::fs::write(dir.join("job.gcode"), gcode).expect("gcode");
        dir
    }

    #[test]
    fn the_json_has_the_steppers_position_and_errors_of_the_run() {
        let dir = sd("run", "G28\nG1 X10 Y20 Z1 F6000\nG1 X1.2.3\nM114\n");
        let summary = crate::run(&dir, None).expect("runs");
        let json = summary.to_json();
        assert_eq!(json["lines"], 4);
        assert_eq!(json["final_position"][0], 10.0);
        assert_eq!(json["final_position"][1], 20.0);
        assert_eq!(json["errors"][0][0], 3);
        assert!(
            json["errors"][0][1]
                .as_str()
                .is_some_and(|e| e.contains("unable to parse"))
        );
        assert!(json["shutdown"].is_null());
        let steppers = json["steppers"].as_array().expect("steppers");
        assert_eq!(steppers.len(), summary.steppers.len());
        let x = &steppers[0];
        assert_eq!(x["name"], "stepper_x");
        assert_eq!(x["steps"], summary.steppers[0].steps);
        assert_eq!(x["position"], summary.steppers[0].position);
        assert!(x["last_step"].as_f64().is_some_and(|t| t > 0.0));
        std::fs::remove_dir_all(&dir).ok();
    }
}
