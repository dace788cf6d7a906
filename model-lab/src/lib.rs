//! model-lab
