# (Sourced by deploy/deb/build.sh and deploy/arm64/cross.sh: one list of what each package
# holds, so the arm64 build makes every binary the packages ship.)
# What goes on the robot (the nori-robot package) and what runs the simulator (nori-sim).
# shellcheck disable=SC2034
robot_bins=(bus-driver supervisor fleet-agent nori-camera nori-lidar nori-base nori-lift nori-record nori-blackbox nori)
# shellcheck disable=SC2034
sim_bins=(nori-sim nori-stack)
