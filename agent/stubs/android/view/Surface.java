package android.view;

public class Surface {
    private Surface() {
        throw new RuntimeException("Stub!");
    }
}
