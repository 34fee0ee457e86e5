//! End-to-end tests of the host build live in `tests/`.
