"""An example for every command's --help (its epilog), kept in one table so each one is
a command line that works as written from the repository's root. A command module may
instead give its parser an `epilog` of its own; `slscan.cli` keeps that."""

from __future__ import annotations

EXAMPLES: dict[str, str] = {
    "scan": "slscan scan --out sessions/part-001\n"
            "slscan scan --scene config/scenes/sphere_plane.toml --seed 3 --out sessions/sphere\n"
            "slscan scan --rig config/rigs/sim_turntable.toml --scene config/scenes/turntable_demo.toml --views 8 "
            "--out sessions/part-all-round",
    "decode": "slscan decode sessions/part-001\n"
              "slscan decode sessions/part-001 --mode phase_to_height\n"
              "slscan decode sessions/part-all-round --stage-axis calibrations/turntable/stage_axis.json",
    "demo": "slscan demo --out sessions/demo\n"
            "slscan demo --no-inspect --seed 2",
    "import": "slscan import ../shared/data/procam-graycode/capture_0 --patterns config/patterns/opencv_graycode.toml "
              "--projector-size 1024x768 --calibration ../shared/data/procam-graycode/calibration_result.xml "
              "--projector-scale 2 --out sessions/procam-0",
    "review": "slscan review sessions/demo            (a scan session)\n"
              "slscan review calibrations/bench        (a calibration folder)\n"
              "slscan review sessions/bin/outputs/poses.rrd --port 9091",
    "export": "slscan export sessions/demo --format e57 --out demo.e57\n"
              "slscan export sessions/demo --format ply --aligned --deviations --out demo-cad-frame.ply",
    "bench": "slscan bench decode --width 1280 --height 1024 --repeats 3 --no-peers\n"
             "slscan bench sim --repeats 3",
    "bench decode": "slscan bench decode --width 1280 --height 1024 --repeats 3 --no-peers",
    "bench binocular": "slscan bench binocular --scenes 1 --imports 1 --repeats 1\n"
                 "slscan bench binocular --scenes 3 --seed 219780649385936647750815756770131625442 --json "
                 "--out binobench.json",
    "bench import": "slscan bench import --skip-procam",
    "bench sim": "slscan bench sim --repeats 3",
    "bench demo": "slscan bench demo --parts 2",
    "bench views": "slscan bench views --out viewbench/demo --views 8 --width 640 --height 512\n"
                 "slscan bench views --out viewbench/ctc01 --part ctc01 --views 8",
    "devices": "slscan devices --probe",
    "devices lightcrafter-images": "slscan devices lightcrafter-images --rig config/rigs/lightcrafter_uvc_box.toml "
                                   "--out lcr-images",
    "calibrate": "slscan calibrate --out calibrations/bench                   (the simulated bench rig)\n"
                 "slscan calibrate --from calibrations/bench/capture --drop-outliers --out calibrations/bench-2\n"
                 "slscan calibrate --stage-axis --rig config/rigs/sim_turntable.toml --out calibrations/turntable\n"
                 "slscan calibrate --covariance-check 30 --seed 5100 --out calibrations/covariance-check",
    "cad": "slscan cad config/parts/demo_part.step\n"
           "slscan cad config/parts/demo_part.step --sample 20000 --repeats 3",
    "bench cad": "slscan bench cad ../shared/data/step/nist_ctc_01_asme1_rd.stp --copies 1,4,16",
    "verify": "slscan verify --out verify/bench                                (the simulated bench rig)\n"
              "slscan verify --leave-one-out ../shared/data/procam-graycode --layout opencv-graycode "
              "--projector-size 1024x768 --board config/boards/procam_chess_9x7_75mm.toml --pose-folders 'capture_*' "
              "--out verify/procam",
    "coverage": "slscan coverage --case sphere-radius --scans 200 --seed 5 --json\n"
                "slscan coverage --case plate-flatness --case plate-sq --scans 200 --seed 6 --calibrated "
                "--out coverage/calibrations --processes 2",
    "register": "slscan register sessions/demo config/parts/demo_part.step --coarse sac-ia --json\n"
                "slscan register sessions/part-all-round/view_001 sessions/part-all-round/view_000 --json",
    "inspect": "slscan inspect sessions/demo --tolerances config/parts/demo_part.toml   (the part program names "
               "its CAD)\n"
               "slscan inspect sessions/part-all-round --tolerances config/parts/demo_part.toml",
    "pose": "slscan pose sessions/bin --part config/parts/nickel_tab.toml --method sac-ia",
    "bench pose": "slscan bench pose --seeds 0 1 2 --methods sac-ia",
    "segment": "slscan segment sessions/demo --radius 12",
    "bench segment": "slscan bench segment --seeds 0 1 --radius 12",
    "segscore": "slscan segscore labels.npy truth.npy --json",
    "station": "slscan station config/parts/demo_part.toml --auto --parts 5 --out station-data",
    "results": "slscan results --data station-data --program config/parts/demo_part.toml --report --out reports/demo\n"
               "slscan results --data station-data --status fail --csv --out failed.csv\n"
               "slscan results --data station-data --program config/parts/demo_part.toml --report --out reports/base "
               "--baseline 1-25 --save-limits limits.json --exclude '7=fixture loose'\n"
               "slscan results --data station-data --program config/parts/demo_part.toml --report --out reports/now "
               "--limits limits.json --rules all\n"
               "slscan results --data station-data --program config/parts/demo_part.toml --dfq --out values.dfq",
    "batch": "slscan batch station-data/sessions/demo-part/* --program config/parts/demo_part.toml --workers 2",
    "bench batch": "slscan bench batch station-data/sessions/demo-part/* --program config/parts/demo_part.toml",
}


def epilog(command: str) -> str | None:
    """The `examples:` block of a command's --help, or None when the table has none."""
    text = EXAMPLES.get(command)
    return None if text is None else "examples:\n" + "\n".join("  " + line for line in text.splitlines())
