"""Makes docs/img/ball_authored.png: frames of the built-in `ball` scene's replay (the bars
authored by `dmarionette author examples/keyframes_ball_kick.toml`), seen from the side.

Run:  python docs/img/ball_authored.py   (needs the 'viz' extra; about a minute on first compile)
"""

from pathlib import Path

from dmarionette.marionette.rollout import simulate_marionette
from dmarionette.marionette.solver import MarionetteModel
from dmarionette.render.frames import render_marionette_frames
from dmarionette.scene.scene import load_scene

TIMES = (0.0, 0.4, 0.66, 1.3, 2.0, 2.5)  # start, the foot on the ball, the kick keyframe, back, forward, the end


def main() -> Path:
    scene = load_scene("ball")
    trajectory = simulate_marionette(MarionetteModel(scene), scene.duration, progress=False)
    return render_marionette_frames(Path(__file__).with_suffix(".png"), trajectory, TIMES,
                                    title="ball_authored: the right foot kicks the ball, the puppet follows it "
                                          "(bars authored from keyframes)",
                                    ground_height=scene.ground_height, ball_radius=scene.ball.radius)


if __name__ == "__main__":
    print(main())
