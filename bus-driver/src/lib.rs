//! bus-driver
