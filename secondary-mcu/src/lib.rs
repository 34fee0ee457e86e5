//! Secondary boards (AVR, SAMD, LPC, STM32) running stock Klipper MCU
//! firmware, driven as Klipper's host drives them: identify, data dictionary,
//! config, clock synchronisation and `queue_step` (issue #6 and after).
#![cfg_attr(not(feature = "std"), no_std)]
