"""The jobs users run, with no ROS and no argparse: simulate, reconstruct, calibrate, report, demo, import, export.

Each takes plain values and typed settings, returns its results in memory, and writes each
output file once. The command line (robot_ct_ros.cli), the nodes (robot_ct_ros.nodes) and the
benchmarks call them. Import the module you need (``robot_ct_ros.jobs.calibrate``, ...): this
package imports nothing itself, so that a job does not load the others' dependencies.
"""
