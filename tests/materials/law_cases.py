"""The laws the materials tests run on: the paper's two tissues and one case of each family."""

from needletissue import materials

LAWS = {
    "muscle": ("mooney_rivlin_5", materials.get("muscle").parameters),
    "mr5_positive": ("mooney_rivlin_5", dict(C10=0.2, C01=0.05, C20=0.01, C11=0.004, C02=0.002)),
    "mooney_rivlin": ("mooney_rivlin", dict(C10=0.2, C01=0.05)),
    "neo_hooke": ("neo_hooke", dict(mu=0.3)),
    "yeoh": ("yeoh", dict(C10=0.1, C20=-0.01, C30=0.002)),
    "adipose": ("ogden", materials.get("adipose").parameters),
    "ogden3": ("ogden", dict(mu=[0.2, -0.01, 0.003], alpha=[1.5, -2.0, 9.0])),
}
