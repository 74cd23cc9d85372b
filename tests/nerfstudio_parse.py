"""Run by nerfstudio's own interpreter (tests/test_external_nerfacto.py), not by pytest: parse
command lines with ns-train's and ns-render's own tyro parsers, without running them, and
print what each chose as one JSON list.

    python nerfstudio_parse.py '[["ns-train", "nerfacto", ...], ["ns-render", "dataset", ...]]'

A command line the parser refuses exits with tyro's status (2) and its message on stderr.
"""

import json
import sys


def train(args: list) -> dict:
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion  # what ns-train's entrypoint parses

    config = tyro.cli(AnnotatedBaseConfigUnion, args=args)
    datamanager, model = config.pipeline.datamanager, config.pipeline.model
    sampler = getattr(datamanager, "pixel_sampler", None)
    return {"method": config.method_name, "data": str(config.data), "output_dir": str(config.output_dir),
            "experiment_name": config.experiment_name, "timestamp": config.timestamp,
            "max_num_iterations": config.max_num_iterations, "seed": config.machine.seed,
            "device_type": config.machine.device_type, "implementation": getattr(model, "implementation", None),
            "rays": getattr(datamanager, "train_num_rays_per_batch", None),
            "ignore_mask": getattr(sampler, "ignore_mask", None),
            "log2_hashmap_size": getattr(model, "log2_hashmap_size", None),
            "background_color": model.background_color,
            "evaluations": [config.steps_per_eval_batch, config.steps_per_eval_image, config.steps_per_eval_all_images],
            "quit_on_train_completion": config.viewer.quit_on_train_completion, "vis": config.vis,
            "dataparser": type(datamanager.dataparser).__name__,
            "load_3D_points": getattr(datamanager.dataparser, "load_3D_points", None)}


def render(args: list) -> dict:
    import tyro
    from nerfstudio.scripts.render import Commands  # what ns-render's entrypoint parses

    command = tyro.cli(Commands, args=args)
    return {"command": type(command).__name__, "load_config": str(command.load_config), "data": str(command.data),
            "output_path": str(command.output_path), "split": command.split,
            "rendered_output_names": command.rendered_output_names, "image_format": command.image_format}


if __name__ == "__main__":
    parsed = []
    for argv in json.loads(sys.argv[1]):
        parsed.append({"ns-train": train, "ns-render": render}[argv[0]](argv[1:]))
    print(json.dumps(parsed))
