"""The bag-of-words vocabulary and its keyframe database: training, words, scores, files,
checkpoints and the `fleetslam vocabulary` command."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import TUM_RPY, require
from test_loop_closing import _flip_bits
from fleetslam.backend.place_recognition import KeyframeDatabase
from fleetslam.backend.places import make_database
from fleetslam.backend.vocabulary import BowDatabase, Vocabulary, load_vocabulary
from fleetslam.cloud.session.session_state import CHECKPOINT_CLASSES
from fleetslam.config import PlaceRecognitionConfig
from fleetslam.wire import data_tree


@pytest.fixture(scope="module")
def world():
    """400 distinct features ("prototypes"); an image sees 60 of them with sensor noise."""
    rng = np.random.default_rng(0)
    prototypes = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    images = [_flip_bits(rng, prototypes[rng.choice(400, 60, replace=False)], 8)
              for _ in range(120)]
    return rng, prototypes, images


def test_a_vocabulary_gives_a_feature_seen_again_its_word(world):
    rng, prototypes, images = world
    vocabulary = Vocabulary.train(images, branching=8, levels=3, seed=1)
    assert 100 <= vocabulary.n_words <= 8 ** 3
    # New noisy views of each prototype mostly land in the word of the prototype itself:
    # a word is a feature, not a random bucket (random words would agree 1 in n_words).
    again = vocabulary.words(_flip_bits(rng, prototypes, 8))
    assert np.mean(again == vocabulary.words(prototypes)) > 0.8
    ids, weights = vocabulary.bow(images[0])
    assert np.all(np.diff(ids) > 0) and weights.sum() == pytest.approx(1.0)


def test_bag_of_words_finds_the_keyframe_that_shares_the_features(world, tmp_path):
    rng, prototypes, images = world
    path = tmp_path / "v.npz"
    Vocabulary.train(images, branching=8, levels=3, seed=1, trained_on="test").save(path)
    config = PlaceRecognitionConfig(method="bag_of_words", vocabulary=str(path))
    db = make_database(config)
    assert isinstance(db, BowDatabase)
    places = [rng.choice(400, 80, replace=False) for _ in range(6)]
    for k, p in enumerate(places):
        db.add(f"kf{k}", _flip_bits(rng, prototypes[p], 8))
    query = _flip_bits(rng, prototypes[places[3][:50]], 8)
    found = db.query(query)
    assert found and found[0].key == "kf3" and 0 < found[0].score <= 1
    assert found[0].score > 2 * max([c.score for c in found[1:]], default=0)
    allowed = np.ones(6, bool)
    allowed[3] = False
    assert all(c.key != "kf3" for c in db.query(query, allowed))
    assert db.query(query, np.zeros(6, bool)) == []
    # A checkpointed database answers the same after restore.
    restored = data_tree.loads(data_tree.dumps(db, CHECKPOINT_CLASSES), "test",
                               CHECKPOINT_CLASSES, 1 << 30)
    assert [c.key for c in restored.query(query)] == [c.key for c in found]


def test_vocabulary_files_and_settings_are_checked(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, centres=np.zeros((3, 32), np.uint8))
    with pytest.raises(ValueError, match="bad.npz: not a vocabulary"):
        Vocabulary.load(bad)
    with pytest.raises(ValueError, match="missing.npz: not a vocabulary"):
        load_vocabulary(str(tmp_path / "missing.npz"))
    with pytest.raises(ValueError, match="needs place_recognition.vocabulary"):
        make_database(PlaceRecognitionConfig(method="bag_of_words"))
    with pytest.raises(ValueError, match="'dbow' is not one of"):
        make_database(PlaceRecognitionConfig(method="dbow"))
    assert isinstance(make_database(PlaceRecognitionConfig()), KeyframeDatabase)


def test_the_vocabulary_command_trains_on_a_real_sequence(tmp_path, capsys):
    from fleetslam.cli import main

    out = tmp_path / "voc.npz"
    assert main(["--quiet", "vocabulary", "--images", str(require(TUM_RPY)), "--every", "15",
                 "--out", str(out)]) == 0
    vocabulary = Vocabulary.load(out)
    assert vocabulary.n_words > 1000 and str(TUM_RPY) in vocabulary.trained_on
    assert "bag_of_words" in capsys.readouterr().out
    assert main(["vocabulary", "--images", str(tmp_path / "nowhere"), "--out",
                 str(out)]) == 2
    assert "no such image folder" in capsys.readouterr().err
