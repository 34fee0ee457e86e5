//! The GPIO ports the board's pins are on, by index (0 = A).

use embassy_stm32::pac;

/// Bytes between two GPIO ports' registers.
pub const STRIDE: usize = 0x400;

/// The GPIO port with index `index` (0 = A, up to H).
pub fn port(index: u8) -> Option<pac::gpio::Gpio> {
    Some(match index {
        0 => pac::GPIOA,
        1 => pac::GPIOB,
        2 => pac::GPIOC,
        3 => pac::GPIOD,
        4 => pac::GPIOE,
        5 => pac::GPIOF,
        6 => pac::GPIOG,
        7 => pac::GPIOH,
        _ => return None,
    })
}
