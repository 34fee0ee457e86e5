//! `board/budget.toml`: the firmware's size budget and image layout.
//!
//! Only the flat `key = value` subset of TOML is accepted (integers in
//! decimal or `0x` hex, double-quoted strings, `#` comments); anything else
//! is an error naming the line.

use std::collections::HashMap;
use std::path::Path;

/// The firmware's limits and layout.
#[derive(Debug, PartialEq, Eq)]
pub struct Budget {
    /// The layouts an image may be linked for: where its vector table
    /// (the application) starts and the flash it may fill, KiB.
    pub layouts: Vec<(u64, u64)>,
    /// The layout's flash budget, KiB (the first layout's until
    /// [`Self::select_layout`]).
    pub flash_kib: u64,
    /// Static RAM budget, KiB.
    pub ram_kib: u64,
    /// Start of the RAM bank the stack and statics live in; nothing is
    /// mapped below it, so a stack at its bottom faults on overflow.
    pub ram_base: u64,
    /// Least stack, KiB, between `ram_base` and the statics.
    pub stack_kib: u64,
    /// Headroom, KiB, the static worst-case stack estimate must leave.
    pub stack_margin_kib: u64,
    /// Interrupt handlers (symbol names) and the NVIC priority the
    /// firmware gives each (0 highest): handlers of one level do not
    /// preempt each other.
    pub irq_priorities: Vec<(String, u64)>,
    /// The layout's application address (its vector table's).
    pub app_base: u64,
    /// Symbol name of the stepper timer's interrupt handler.
    pub stepper_irq: String,
    /// Position of that interrupt in the device vector table.
    pub stepper_irq_number: u64,
    /// Substrings of (mangled) symbol names that must occur in the ELF.
    pub required_code: Vec<String>,
    /// Rust paths (`a::b`) no linked symbol may lie under.
    pub forbidden_code: Vec<String>,
    /// Base address of the instruction TCM.
    pub itcm_base: u64,
    /// Size of the instruction TCM, KiB.
    pub itcm_kib: u64,
    /// Base address of the data TCM.
    pub dtcm_base: u64,
    /// Size of the data TCM, KiB.
    pub dtcm_kib: u64,
    /// Substrings of (mangled) names of functions the stepper interrupt
    /// may reach outside ITCM (and that the walk does not go on from).
    pub itcm_exempt: Vec<String>,
    /// Rust paths of statics that must lie in DTCM.
    pub dtcm_data: Vec<String>,
    /// Rust paths of statics a DMA reaches, which must lie in the MPU's
    /// non-cacheable region (`__dma_region_start..__dma_region_end`).
    pub dma_data: Vec<String>,
    /// Functions (symbol names) the reset handler must reach over direct
    /// calls.
    pub boot_calls: Vec<String>,
}

#[derive(Debug)]
enum Value {
    Int(u64),
    Str(String),
}

impl Budget {
    /// Reads and checks the budget file.
    pub fn load(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Self::parse(&text).map_err(|e| format!("{}: {e}", path.display()))
    }

    fn parse(text: &str) -> Result<Self, String> {
        let mut values = HashMap::new();
        for (number, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or_default().trim();
            if line.is_empty() {
                continue;
            }
            let (key, value) = line
                .split_once('=')
                .ok_or_else(|| format!("line {}: expected `key = value`", number + 1))?;
            let value =
                parse_value(value.trim()).map_err(|e| format!("line {}: {e}", number + 1))?;
            values.insert(key.trim().to_string(), value);
        }
        let mut int = |key: &str| match values.remove(key) {
            Some(Value::Int(v)) => Ok(v),
            Some(Value::Str(_)) => Err(format!("`{key}` must be a number")),
            None => Err(format!("`{key}` is missing")),
        };
        let (ram_kib, stepper_irq_number) = (int("ram_kib")?, int("stepper_irq_number")?);
        let (ram_base, stack_kib) = (int("ram_base")?, int("stack_kib")?);
        let stack_margin_kib = int("stack_margin_kib")?;
        let (itcm_base, itcm_kib) = (int("itcm_base")?, int("itcm_kib")?);
        let (dtcm_base, dtcm_kib) = (int("dtcm_base")?, int("dtcm_kib")?);
        let mut string = |key: &str| match values.remove(key) {
            Some(Value::Str(s)) => Ok(s),
            Some(Value::Int(_)) => Err(format!("`{key}` must be a string")),
            None => Err(format!("`{key}` is missing")),
        };
        let stepper_irq = string("stepper_irq")?;
        let list = |text: String| -> Vec<String> {
            text.split(',').map(|s| s.trim().to_string()).collect()
        };
        let required_code = list(string("required_code")?);
        let forbidden_code = list(string("forbidden_code")?);
        let itcm_exempt = list(string("itcm_exempt")?);
        let dtcm_data = list(string("dtcm_data")?);
        let dma_data = list(string("dma_data")?);
        let boot_calls = list(string("boot_calls")?);
        let layouts = list(string("layouts")?)
            .into_iter()
            .map(|pair: String| {
                let fail = || format!("`layouts`: `{pair}` is not APP_BASE:FLASH_KIB");
                let (base, kib) = pair.split_once(':').ok_or_else(fail)?;
                match (parse_value(base.trim()), parse_value(kib.trim())) {
                    (Ok(Value::Int(base)), Ok(Value::Int(kib))) => Ok((base, kib)),
                    _ => Err(fail()),
                }
            })
            .collect::<Result<Vec<_>, String>>()?;
        let &(app_base, flash_kib) = layouts.first().ok_or("`layouts` is empty")?;
        let irq_priorities = list(string("irq_priorities")?)
            .into_iter()
            .map(|pair: String| {
                let (name, level) = pair.split_once(':').unwrap_or((&pair, ""));
                let level = level
                    .trim()
                    .parse()
                    .map_err(|_| format!("`irq_priorities`: `{pair}` is not NAME:LEVEL"))?;
                Ok((name.trim().to_string(), level))
            })
            .collect::<Result<_, String>>()?;
        if let Some(key) = values.keys().next() {
            return Err(format!("unknown key `{key}`"));
        }
        Ok(Self {
            layouts,
            flash_kib,
            ram_kib,
            ram_base,
            stack_kib,
            stack_margin_kib,
            irq_priorities,
            app_base,
            stepper_irq,
            stepper_irq_number,
            required_code,
            forbidden_code,
            itcm_base,
            itcm_kib,
            dtcm_base,
            dtcm_kib,
            itcm_exempt,
            dtcm_data,
            dma_data,
            boot_calls,
        })
    }
}

impl Budget {
    /// Takes the layout whose application starts at `vector_table` (the
    /// image's): its address and flash budget.
    pub fn select_layout(&mut self, vector_table: u64) -> Result<(), String> {
        let &(app_base, flash_kib) = (self.layouts.iter())
            .find(|(base, _)| *base == vector_table)
            .ok_or_else(|| {
                format!("the vector table is at {vector_table:#010x}, where no layout of the budget starts")
            })?;
        (self.app_base, self.flash_kib) = (app_base, flash_kib);
        Ok(())
    }
}

fn parse_value(text: &str) -> Result<Value, String> {
    if let Some(s) = text.strip_prefix('"').and_then(|t| t.strip_suffix('"')) {
        return Ok(Value::Str(s.to_string()));
    }
    let digits = text.replace('_', "");
    let parsed = match digits.strip_prefix("0x") {
        Some(hex) => u64::from_str_radix(hex, 16),
        None => digits.parse(),
    };
    parsed
        .map(Value::Int)
        .map_err(|_| format!("`{text}` is neither a number nor a string"))
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = "layouts = \"0x0802_0000:384, 0x0800_0000:512\" # comment\nram_kib = 256\n\
                        ram_base = 0x2400_0000\nstack_kib = 64\nstack_margin_kib = 8\n\
                        irq_priorities = \"TIM5:0, SPI6:4\"\n\
                        stepper_irq = \"TIM5\"\nstepper_irq_number = 50\n\
                        required_code = \"a..b, c\"\nforbidden_code = \"x::y\"\n\
                        itcm_base = 0\nitcm_kib = 64\ndtcm_base = 0x2000_0000\ndtcm_kib = 128\n\
                        itcm_exempt = \"panicking\"\ndtcm_data = \"a::ENGINE\"\n\
                        dma_data = \"a::DMA\"\nboot_calls = \"init\"\n";

    #[test]
    fn parses_the_shipped_layout() {
        let b = Budget::parse(GOOD).expect("valid");
        assert_eq!(b.app_base, 0x0802_0000);
        assert_eq!(
            (b.flash_kib, b.ram_kib, b.stepper_irq_number),
            (384, 256, 50)
        );
        assert_eq!((b.ram_base, b.stack_kib), (0x2400_0000, 64));
        assert_eq!(b.stepper_irq, "TIM5");
        assert_eq!(b.required_code, ["a..b", "c"]);
        assert_eq!(b.forbidden_code, ["x::y"]);
        assert_eq!(b.stack_margin_kib, 8);
        assert_eq!(
            (b.itcm_base, b.itcm_kib, b.dtcm_base, b.dtcm_kib),
            (0, 64, 0x2000_0000, 128)
        );
        assert_eq!(b.itcm_exempt, ["panicking"]);
        assert_eq!(
            (b.dtcm_data, b.dma_data),
            (vec!["a::ENGINE".to_string()], vec!["a::DMA".to_string()])
        );
        assert_eq!(b.boot_calls, ["init"]);
        assert_eq!(
            b.irq_priorities,
            [("TIM5".to_string(), 0), ("SPI6".to_string(), 4)]
        );
        assert_eq!(b.layouts, [(0x0802_0000, 384), (0x0800_0000, 512)]);
        let bad = GOOD.replace("SPI6:4", "SPI6");
        assert_eq!(
            Budget::parse(&bad),
            Err("`irq_priorities`: `SPI6` is not NAME:LEVEL".into())
        );
    }

    #[test]
    fn the_repository_budget_file_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../board/budget.toml");
        let mut b = Budget::load(&path).expect("board/budget.toml parses");
        // The STM32H723ZE's 512 KiB less the bootloader's 128 KiB first.
        assert_eq!((b.flash_kib, b.ram_kib), (384, 256));
        assert_eq!(b.app_base, 0x0802_0000);
        // Without the bootloader: all of it.
        b.select_layout(0x0800_0000)
            .expect("a layout without bootloader");
        assert_eq!((b.app_base, b.flash_kib), (0x0800_0000, 512));
        assert_eq!(
            b.select_layout(0x0801_0000),
            Err("the vector table is at 0x08010000, where no layout of the budget starts".into())
        );
    }

    #[test]
    fn errors_name_the_problem() {
        let missing = GOOD.replace("ram_kib = 256\n", "");
        assert_eq!(Budget::parse(&missing), Err("`ram_kib` is missing".into()));
        let bad = GOOD.replace("256", "lots");
        assert_eq!(
            Budget::parse(&bad),
            Err("line 2: `lots` is neither a number nor a string".into())
        );
        let extra = format!("{GOOD}heap_kib = 8\n");
        assert_eq!(Budget::parse(&extra), Err("unknown key `heap_kib`".into()));
    }
}
