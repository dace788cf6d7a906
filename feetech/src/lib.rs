//! feetech
