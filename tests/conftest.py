import pytest
import torch

from course_utils import models


@pytest.fixture(scope="session")
def tokenizer():
    return models.load_tokenizer(models.TINY)


@pytest.fixture(scope="session")
def tiny_model(tokenizer):
    model = models.tiny_qwen2(len(tokenizer), seed=0)
    model.generation_config.eos_token_id = tokenizer.eos_token_id
    return model.eval()


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(0)
