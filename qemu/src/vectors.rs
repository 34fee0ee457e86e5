//! The interrupt part of the vector table (cortex-m-rt's `device`
//! feature: this crate provides `__INTERRUPTS`): mps2-an500's 32 lines,
//! the five this firmware uses wired to their handlers.

/// One vector: a handler, or a line no handler is installed for.
#[derive(Clone, Copy)]
pub union Vector {
    handler: extern "C" fn(),
    reserved: usize,
}

/// A line nothing should raise: a vector of 0, whose use faults (the
/// hard fault handler reports it and stops QEMU).
const UNUSED: Vector = Vector { reserved: 0 };

/// The interrupt vectors, IRQ 0 first.
#[unsafe(link_section = ".vector_table.interrupts")]
#[unsafe(no_mangle)]
pub static __INTERRUPTS: [Vector; 32] = {
    let mut table = [UNUSED; 32];
    table[crate::machine::Irq::Uart0Rx as usize] = Vector {
        handler: crate::uart_console::uart0_rx,
    };
    table[crate::machine::Irq::Uart1Rx as usize] = Vector {
        handler: crate::uart_link::uart1_rx,
    };
    table[crate::machine::Irq::Uart1Tx as usize] = Vector {
        handler: crate::uart_link::uart1_tx,
    };
    table[crate::machine::Irq::Timer0 as usize] = Vector {
        handler: crate::step_timer::timer0,
    };
    table[crate::machine::Irq::DualTimer as usize] = Vector {
        handler: crate::heater_io::dualtimer,
    };
    table
};
