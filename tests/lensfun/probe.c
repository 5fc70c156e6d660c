/* Round-trip probe for tests/lensfun.rs: loads a lensfun database file with liblensfun (the
 * real consumer), finds the lens, and prints what lensfun's correction does at given pixels.
 *
 * usage: probe FILE MAKER MODEL CROP WIDTH HEIGHT FOCAL APERTURE DISTANCE < points
 * stdin: "x y" per line (pixel coordinates). stdout per point:
 *   "tca X Y XR YR XB YB"  source positions of R and B for the corrected pixel (LF_MODIFY_TCA)
 *   "vig X Y GAIN"         the factor lensfun's vignetting correction applies (LF_MODIFY_VIGNETTING)
 *   "dist X Y XD YD"       the source (distorted) position of the corrected pixel (LF_MODIFY_DISTORTION)
 * Exit 2 when the file does not load or the lens is not found. */
#include <lensfun.h>
#include <stdio.h>
#include <stdlib.h>

int main(int argc, char **argv) {
    if (argc != 10) { fprintf(stderr, "usage: probe FILE MAKER MODEL CROP W H FOCAL APERTURE DISTANCE\n"); return 2; }
    float crop = atof(argv[4]), focal = atof(argv[7]), aperture = atof(argv[8]), distance = atof(argv[9]);
    int w = atoi(argv[5]), h = atoi(argv[6]);
    lfDatabase *db = lf_db_new();
    if (lf_db_load_file(db, argv[1]) != LF_NO_ERROR) { fprintf(stderr, "cannot load %s\n", argv[1]); return 2; }
    const lfLens **lenses = lf_db_find_lenses_hd(db, NULL, argv[2], argv[3], 0);
    if (!lenses || !lenses[0]) { fprintf(stderr, "lens %s / %s not found\n", argv[2], argv[3]); return 2; }
    const lfLens *lens = lenses[0];
    printf("lens %s\n", lf_mlstr_get(lens->Model));
    lfModifier *tm = lf_modifier_new(lens, crop, w, h);
    int tf = lf_modifier_initialize(tm, lens, LF_PF_F32, focal, aperture, distance, 1.0, lens->Type, LF_MODIFY_TCA, 0);
    lfModifier *vm = lf_modifier_new(lens, crop, w, h);
    int vf = lf_modifier_initialize(vm, lens, LF_PF_F32, focal, aperture, distance, 1.0, lens->Type, LF_MODIFY_VIGNETTING, 0);
    lfModifier *dm = lf_modifier_new(lens, crop, w, h);
    int df = lf_modifier_initialize(dm, lens, LF_PF_F32, focal, aperture, distance, 1.0, lens->Type, LF_MODIFY_DISTORTION, 0);
    printf("flags tca=%d vignetting=%d distortion=%d\n", (tf & LF_MODIFY_TCA) != 0, (vf & LF_MODIFY_VIGNETTING) != 0, (df & LF_MODIFY_DISTORTION) != 0);
    double x, y;
    while (scanf("%lf %lf", &x, &y) == 2) {
        float res[6];
        if (tf & LF_MODIFY_TCA) {
            if (lf_modifier_apply_subpixel_distortion(tm, (float)x, (float)y, 1, 1, res))
                printf("tca %g %g %.5f %.5f %.5f %.5f\n", x, y, res[0], res[1], res[4], res[5]);
        }
        if (df & LF_MODIFY_DISTORTION) {
            float xy[2];
            if (lf_modifier_apply_geometry_distortion(dm, (float)x, (float)y, 1, 1, xy))
                printf("dist %g %g %.5f %.5f\n", x, y, xy[0], xy[1]);
        }
        if (vf & LF_MODIFY_VIGNETTING) {
            float px[3] = {1.0f, 1.0f, 1.0f};
            if (lf_modifier_apply_color_modification(vm, px, (float)x, (float)y, 1, 1, LF_CR_3(RED, GREEN, BLUE), 3 * sizeof(float)))
                printf("vig %g %g %.6f\n", x, y, px[1]);
        }
    }
    lf_modifier_destroy(tm);
    lf_modifier_destroy(vm);
    lf_modifier_destroy(dm);
    lf_free(lenses);
    lf_db_destroy(db);
    return 0;
}
